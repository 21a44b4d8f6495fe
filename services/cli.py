"""``foldwise``: the command line of every role.

Sub-commands of the render and train workers live beside their code
(``workers/render/cli.py``, ``workers/train/cli.py``) and are registered here; each keeps
its heavy imports (bpy, torch) inside the command so that ``foldwise api`` never loads them.
"""

from __future__ import annotations

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False, help=__doc__.split("\n")[0])


def _register_worker_commands() -> None:
    from workers.render import cli as render_cli
    from workers.train import cli as train_cli

    render_cli.register(app)
    train_cli.register(app)


def main() -> None:
    _register_worker_commands()
    app()


if __name__ == "__main__":
    main()
