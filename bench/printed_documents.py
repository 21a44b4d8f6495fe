"""Printed business documents of one kind, drawn by code: targets and their lookalikes.

A user who trains foldwise on their own printed sheets (invoices, forms, covers) meets other
sheets of the same kind in the wild: the same letterhead, the same table, other words. This
module draws such a family so that the benchmarks can score a detector where lookalikes are
the hard negatives:

* ``targets``: one sheet of each of five companies' templates (a letterhead, logo, table and
  footer of its own), each with its own title, addresses, rows and text: the detector's classes;
* ``lookalikes``: more sheets of each target's *template* with other contents (the user's other
  forms: the same letterhead and footer), sheets of other companies in the same layout, and
  plain text pages.

Every sheet is A4 (1 : √2), drawn with PIL and the DejaVu fonts matplotlib ships. Nothing here is
read by foldwise's training unless a config names the folder it writes
(``assets.objects: var/bench/documents/targets``)::

    python bench/printed_documents.py --out var/bench/documents
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

WIDTH, HEIGHT = 620, 877  # A4 at about 75 dpi
SYLLABLES = (
    "ka",
    "lo",
    "mi",
    "ter",
    "an",
    "sol",
    "vi",
    "dor",
    "pe",
    "ru",
    "sen",
    "ta",
    "bel",
    "mo",
    "ri",
    "gan",
    "el",
    "cor",
)
COLUMN_NAMES = (
    ("Item", "Pos.", "No.", "Ref"),
    ("Description", "Article", "Service", "Product"),
    ("Qty", "Units", "Amount"),
    ("Price", "Rate", "Unit price"),
    ("Total", "Sum", "Net"),
)
TITLES = (
    "INVOICE",
    "DELIVERY NOTE",
    "PURCHASE ORDER",
    "QUOTATION",
    "STATEMENT",
    "RECEIPT",
    "CREDIT NOTE",
    "REMITTANCE",
)


def _font(size: int, bold: bool = False, serif: bool = False):
    import matplotlib
    from PIL import ImageFont

    name = ("DejaVuSerif" if serif else "DejaVuSans") + ("-Bold" if bold else "") + ".ttf"
    return ImageFont.truetype(str(Path(matplotlib.get_data_path()) / "fonts/ttf" / name), size)


def _word(rng: np.random.Generator, capital: bool = False) -> str:
    word = "".join(rng.choice(SYLLABLES, size=int(rng.integers(1, 4))))
    return word.capitalize() if capital else word


def _sentence(rng: np.random.Generator, words: int) -> str:
    return " ".join(_word(rng, capital=index == 0) for index in range(words))


class Template:
    """One company's letterhead and layout: the part a family of its sheets shares."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.colour = tuple(int(v) for v in rng.integers(20, 180, size=3))
        self.accent = tuple(int(v) for v in rng.integers(60, 230, size=3))
        self.name = f"{_word(rng, True)} {_word(rng, True)} {rng.choice(['GmbH', 'Ltd', 'S.A.', 'Inc.'])}"
        self.address = f"{int(rng.integers(1, 200))} {_word(rng, True)} Street, {_word(rng, True)}"
        self.logo = int(rng.integers(0, 3))
        self.serif = bool(rng.integers(0, 2))
        # The layout is the template's too: where blocks sit, how large the type is, what the
        # table's columns are called. Sheets of one template share it; other templates differ.
        self.columns = tuple(str(rng.choice(pool)) for pool in COLUMN_NAMES)
        self.title_size = int(rng.integers(24, 36))
        self.text_size = int(rng.integers(12, 16))
        self.table_top = int(rng.integers(290, 360))
        self.row_height = int(rng.integers(21, 28))
        self.header_height = int(rng.integers(70, 130))

    def draw(self, rng: np.random.Generator, title: str) -> np.ndarray:
        """A sheet of this template with contents drawn from ``rng``: (HEIGHT, WIDTH, 3) uint8 RGB."""
        from PIL import Image, ImageDraw

        page = Image.new("RGB", (WIDTH, HEIGHT), (252, 251, 247))
        pen = ImageDraw.Draw(page)
        # Letterhead: logo, name, address, a rule in the company's colour.
        x, y = 40, 36
        if self.logo == 0:
            pen.ellipse((x, y, x + 56, y + 56), fill=self.colour)
            pen.polygon([(x + 12, y + 44), (x + 28, y + 10), (x + 44, y + 44)], fill=self.accent)
        elif self.logo == 1:
            pen.rectangle((x, y, x + 56, y + 56), fill=self.colour)
            pen.ellipse((x + 14, y + 14, x + 42, y + 42), fill=self.accent)
        else:
            pen.polygon([(x + 28, y), (x + 56, y + 28), (x + 28, y + 56), (x, y + 28)], fill=self.colour)
            pen.rectangle((x + 20, y + 20, x + 36, y + 36), fill=self.accent)
        pen.text((112, 38), self.name, font=_font(26, bold=True, serif=self.serif), fill=self.colour)
        pen.text((112, 74), self.address, font=_font(13, serif=self.serif), fill=(70, 70, 70))
        rule = 8 + self.header_height
        pen.rectangle((40, rule, WIDTH - 40, rule + 4), fill=self.colour)
        # Title and reference: each sheet's own.
        pen.text((40, rule + 20), title, font=_font(self.title_size, bold=True, serif=self.serif), fill=(25, 25, 25))
        reference = f"No. {int(rng.integers(1000, 99999))}   {int(rng.integers(1, 29)):02d}.{int(rng.integers(1, 13)):02d}.20{int(rng.integers(10, 30))}"
        pen.text((40, rule + 28 + self.title_size), reference, font=_font(15, serif=self.serif), fill=(40, 40, 40))
        # Two address blocks.
        for column in (40, 340):
            for line in range(4):
                text = _sentence(rng, int(rng.integers(2, 4)))
                y = rule + 60 + self.title_size + 20 * line
                pen.text(
                    (column, y),
                    text,
                    font=_font(self.text_size + 1, bold=line == 0, serif=self.serif),
                    fill=(30, 30, 30),
                )
        # The table: a header in the company's colour, rows of items.
        top, edges = max(self.table_top, rule + 160 + self.title_size), (40, 100, 330, 400, 480, WIDTH - 40)
        pen.rectangle((40, top, WIDTH - 40, top + 26), fill=self.colour)
        for left, name in zip(edges, self.columns):
            pen.text((left + 6, top + 5), name, font=_font(14, bold=True), fill=(255, 255, 255))
        rows = int(rng.integers(4, 10))
        for row in range(rows):
            y = top + 30 + self.row_height * row
            if row % 2:
                pen.rectangle((40, y - 2, WIDTH - 40, y + self.row_height - 4), fill=(236, 236, 232))
            quantity, price = int(rng.integers(1, 50)), float(rng.integers(100, 99999)) / 100
            cells = (
                str(int(rng.integers(100, 999))),
                _sentence(rng, int(rng.integers(2, 4))),
                str(quantity),
                f"{price:.2f}",
                f"{quantity * price:.2f}",
            )
            for left, text in zip(edges, cells):
                pen.text((left + 6, y), text, font=_font(self.text_size, serif=self.serif), fill=(20, 20, 20))
        bottom = top + 34 + self.row_height * rows
        pen.line((40, bottom, WIDTH - 40, bottom), fill=(60, 60, 60), width=2)
        pen.text(
            (400, bottom + 8),
            f"Total  {float(rng.integers(1000, 999999)) / 100:.2f}",
            font=_font(18, bold=True),
            fill=(20, 20, 20),
        )
        # Body text, to the footer.
        y = bottom + 50
        while y < HEIGHT - 110:
            pen.text(
                (40, y),
                _sentence(rng, int(rng.integers(5, 9))),
                font=_font(self.text_size, serif=self.serif),
                fill=(45, 45, 45),
            )
            y += self.text_size + 6
        # Footer: shared by the template.
        pen.rectangle((40, HEIGHT - 70, WIDTH - 40, HEIGHT - 68), fill=self.colour)
        pen.text(
            (40, HEIGHT - 60), f"{self.name} · {self.address}", font=_font(12, serif=self.serif), fill=(90, 90, 90)
        )
        return np.asarray(page)


def text_page(rng: np.random.Generator) -> np.ndarray:
    """A page of plain text: printed, but of no company's template."""
    from PIL import Image, ImageDraw

    page = Image.new("RGB", (WIDTH, HEIGHT), (250, 250, 250))
    pen = ImageDraw.Draw(page)
    serif = bool(rng.integers(0, 2))
    pen.text((50, 50), _sentence(rng, 4).upper(), font=_font(22, bold=True, serif=serif), fill=(10, 10, 10))
    y = 100
    while y < HEIGHT - 50:
        if rng.random() < 0.08:
            y += 14  # a paragraph break
        pen.text((50, y), _sentence(rng, int(rng.integers(7, 11))), font=_font(14, serif=serif), fill=(30, 30, 30))
        y += 20
    return np.asarray(page)


def make_documents(
    out: Path, n_targets: int = 5, n_same_template: int = 2, n_other_template: int = 4, n_text: int = 3, seed: int = 0
) -> dict:
    """Write ``out/targets/*.png`` (the classes: one sheet of each of ``n_targets`` companies)
    and ``out/lookalikes/*.png`` (``n_same_template`` more sheets of each target's company, one
    sheet each of ``n_other_template`` other companies, ``n_text`` text pages); return their paths."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    companies = [Template(seed * 1000 + index) for index in range(n_targets)]
    others = [Template(seed * 1000 + n_targets + index) for index in range(n_other_template)]
    written: dict[str, list[str]] = {"targets": [], "lookalikes": []}
    sheets = [
        ("targets", f"doc{index + 1}", company, TITLES[index % len(TITLES)]) for index, company in enumerate(companies)
    ]
    sheets += [
        ("lookalikes", f"same{index + 1}-{copy + 1}", company, TITLES[(index + copy + 1) % len(TITLES)])
        for index, company in enumerate(companies)
        for copy in range(n_same_template)
    ]
    sheets += [
        ("lookalikes", f"other{index + 1}", company, TITLES[index % len(TITLES)])
        for index, company in enumerate(others)
    ]
    for kind, name, template, title in sheets:
        (out / kind).mkdir(parents=True, exist_ok=True)
        path = out / kind / f"{name}.png"
        Image.fromarray(template.draw(rng, title)).save(path)
        written[kind].append(str(path))
    for index in range(n_text):
        path = out / "lookalikes" / f"text{index + 1}.png"
        Image.fromarray(text_page(rng)).save(path)
        written["lookalikes"].append(str(path))
    return written


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("var/bench/documents"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    written = make_documents(args.out, seed=args.seed)
    print(
        f"{len(written['targets'])} targets in {args.out / 'targets'}, {len(written['lookalikes'])} lookalikes in {args.out / 'lookalikes'}"
    )


if __name__ == "__main__":
    main()
