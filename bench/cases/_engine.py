"""One engine run for a bench case: ``python -m pipeline <args>`` in this process, its log
kept, and a failure raised with the log's tail or returned (what every case that runs the
engine needs)."""
from __future__ import annotations

from pathlib import Path


def run_engine(args: list[str], what: str, log_file: Path | None = None, echo: int = 0,
               tail: int = 30, check: bool = True) -> int:
    """Run the engine's CLI with ``args``; write its log lines to ``log_file`` (when given),
    print the last ``echo`` of them, and, with ``check``, raise ``RuntimeError`` naming
    ``what`` with the last ``tail`` lines when it exits non-zero. Returns the exit code (a
    case that records a failed run instead of raising passes ``check=False``)."""
    from pipeline.cli import main

    logs: list[str] = []
    rc = main(list(args), log=logs.append)
    if log_file is not None:
        Path(log_file).write_text("\n".join(logs))
    if echo:
        print("\n".join(logs[-echo:]), flush=True)
    if rc != 0 and check:
        raise RuntimeError(f"engine failed ({what}; exit {rc}: {' '.join(args)}):\n"
                           + "\n".join(logs[-tail:]))
    return rc
