"""``python -m studio.inspect``: the deepest true interpenetration of a sequence's ground truth,
the body parts involved and the close-up picture.

In a module of its own: ``studio.inspect`` opens its own :class:`drawing.render.Renderer`, and
pyrender's EGL teardown terminates the process's EGL display, which breaks any other renderer
still open (such as the module-scoped one of ``test_drawing.py``)."""
from __future__ import annotations

import numpy as np
import pytest


def test_inspect_finds_the_deepest_frame_and_draws_it(anny, tmp_path, capsys):
    """python -m studio.inspect on a ground truth where the two bodies overlap in one frame."""
    import cv2

    from body import forward
    from formats.errors import InputError
    from studio.inspect import inspect, main

    V = forward(anny, np.zeros(10), np.zeros((1, anny.num_joints, 3)), np.eye(3)[None],
                np.zeros((1, 3))).vertices[0]
    shifts = [1.5, 0.25, 1.2]  # metres along x: apart, overlapping, apart
    Vs = np.stack([np.stack([V] * 3), np.stack([V + [s, 0, 0] for s in shifts])]).astype(np.float32)
    gt = tmp_path / "Hug 1.npz"
    np.savez(gt, vertices=Vs, faces=np.asarray(anny.faces, np.int32))
    res = inspect(gt)
    assert res.frame == 1 and res.depth_m > 0.01
    assert res.parts and res.parts[0][3] == pytest.approx(res.depth_m, abs=1e-9)
    img = cv2.imread(str(res.png))
    assert img is not None and img.shape[:2] == (900, 900)
    # a frame without contact: nothing inside, still a picture
    res2 = inspect(gt, frame=0, out=tmp_path / "f0.png")
    assert res2.depth_m == 0 and res2.parts == [] and res2.png.exists()
    with pytest.raises(InputError, match=r"Hug 1.npz: vertices \[frame 3\]"):
        inspect(gt, frame=3)
    assert main([str(tmp_path / "missing.npz")]) == 2
    assert "missing.npz" in capsys.readouterr().err
