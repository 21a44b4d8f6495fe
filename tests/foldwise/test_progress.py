"""Progress display: plain lines with an ETA off a terminal, no control codes, no 80-column wrap."""

from __future__ import annotations

import io

from foldwise.progress import CommandProgress, command_console, format_seconds, remaining_seconds


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_line_per_update_with_elapsed_and_eta_when_not_a_terminal():
    stream = io.StringIO()
    clock = FakeClock()
    with CommandProgress(command_console(stream), "fb/easy", total=4, unit="stages", clock=clock) as bar:
        clock.now += 10
        bar.update(1)
        clock.now += 10
        bar.update(1)  # nothing changed: no repeated line
        bar.update(2, description="fb/hard")
    lines = stream.getvalue().splitlines()
    assert lines == [
        "fb/easy: 1/4 stages (25%), elapsed 0:00:10, ETA 0:00:30",
        "fb/hard: 2/4 stages (50%), elapsed 0:00:20, ETA 0:00:20",
    ]


def test_interval_throttles_lines_but_the_last_state_is_always_printed():
    stream = io.StringIO()
    clock = FakeClock()
    with CommandProgress(command_console(stream), "training", 100, "iterations", interval_s=5, clock=clock) as bar:
        for step in range(1, 100):
            clock.now += 0.5
            bar.update(step)
    lines = stream.getvalue().splitlines()
    # a line at step 1, then one per 5 s (10 steps), and the final state on exit
    assert len(lines) == 1 + 99 // 10 + 1
    assert lines[0].startswith("training: 1/100 iterations (1%)")
    assert lines[-1].startswith("training: 99/100 iterations (99%)")


def test_finishing_prints_a_final_line_even_when_throttled():
    stream = io.StringIO()
    clock = FakeClock()
    with CommandProgress(command_console(stream), "rendering", 3, "images", interval_s=60, clock=clock) as bar:
        bar.update(1)
        bar.update(3)
    assert stream.getvalue().splitlines()[-1] == "rendering: 3/3 images (100%), elapsed 0:00:00, ETA 0:00:00"


def test_console_off_a_terminal_neither_wraps_nor_colours():
    stream = io.StringIO()
    console = command_console(stream)
    long_line = "word " * 60
    console.print(f"[bold red]{long_line}[/]")
    assert stream.getvalue() == long_line + "\n"


def test_time_helpers():
    assert format_seconds(3725) == "1:02:05"
    assert format_seconds(None) == "-:--:--"
    assert remaining_seconds(30, 0, 10) is None
    assert remaining_seconds(30, 3, 10) == 70
    assert remaining_seconds(30, 10, 10) == 0
