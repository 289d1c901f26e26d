"""The one error type for bad input files.

Every reader raises :class:`InputError` naming the file, the field and, where it applies, the
frame, so a lab can find the problem without a debugger::

    data/s03/Hug 1.c3d: POINT:LABELS: 12 labels for 39 points
    data/cams/50591643/Hug 1.json: extrinsics.R [frame -]: expected (3, 3), got (3,)
"""
from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Bad input: ``file``, ``field``, optional ``frame`` and what is wrong.

    ``input_error = True`` is the engine's convention for bad data (``pipeline.engine.
    is_input_error``, duck-typed: ``formats`` imports no engine): raised inside a stage it
    fails the node with this one-line message and no traceback, and the CLI exits with 2.
    """

    input_error = True

    def __init__(self, file: str | Path, field: str, msg: str, frame: int | None = None):
        self.file = str(file)
        self.field = field
        self.frame = frame
        self.msg = msg
        where = f"{self.file}: {field}"
        if frame is not None:
            where += f" [frame {frame}]"
        super().__init__(f"{where}: {msg}")

    def __reduce__(self):  # picklable across worker processes (args hold only the message)
        return (type(self), (self.file, self.field, self.msg, self.frame))


def expect_shape(x, spec: str, name: str, file: str | Path = "<memory>", frame: int | None = None):
    """Check an array's shape against a spec such as ``"F C K 3"`` (letters: any size, but the
    same letter must have the same size within one call; digits: exact). Returns x.

    Raises InputError naming ``file`` and the field ``name``.
    """
    import numpy as np

    a = np.asarray(x)
    dims = spec.split()
    if a.ndim != len(dims):
        raise InputError(file, name, f"expected shape ({spec}), got {a.shape}", frame)
    seen: dict[str, int] = {}
    for d, n in zip(dims, a.shape, strict=True):
        if d.isdigit():
            if int(d) != n:
                raise InputError(file, name, f"expected shape ({spec}), got {a.shape}", frame)
        elif seen.setdefault(d, n) != n:
            raise InputError(file, name, f"expected shape ({spec}), got {a.shape}", frame)
    return x
