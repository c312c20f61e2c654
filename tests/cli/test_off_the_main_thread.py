"""The command line called from a thread other than the main one (an embedding program, the
suite's own in-process calls): signals are not its to take there — Python lets only the main
thread set handlers — so it runs without them instead of failing."""

from __future__ import annotations

import threading

from rcan_rtps.cli.main import main


def _in_a_thread(argv: list[str]) -> object:
    out: list[object] = []

    def call() -> None:
        try:
            out.append(main(argv))
        except BaseException as exc:  # what the thread saw is the result
            out.append(exc)

    thread = threading.Thread(target=call)
    thread.start()
    thread.join(60)
    return out[0]


def test_a_command_with_an_event_loop_from_another_thread(tmp_path: object) -> None:
    # `bag play` of a bag that is not there: its loop runs, and it fails before any DDS
    result = _in_a_thread(["bag", "play", f"{tmp_path}/none"])
    assert result == 1, result  # the error exit, not a signal error
