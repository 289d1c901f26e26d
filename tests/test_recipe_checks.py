"""Every recipe value is checked before any stage runs: one message per problem naming the file
and the field, exit code 2, nothing computed."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from pipeline import cli


def _recipe(tmp: Path, videos: dict[str, str] | None = None, **edits) -> Path:
    files = tmp / "files"
    files.mkdir(parents=True, exist_ok=True)
    for name in ("a.ply", "b.ply", "x.c3d", "cal.json", "m.npz"):
        (files / name).write_text(name)
    cams = ["c1", "c2", "c3"]
    videos = videos or {c: "files/v.mp4" for c in cams}
    if not (files / "v.mp4").exists():
        (files / "v.mp4").write_text("not a video")
    raw = {"session": "checks", "cameras": cams,
           "subjects": {"sa": {"scan": "files/a.ply"}, "sb": {"scan": "files/b.ply"}},
           "sequences": {"g/X 1": {"markers_on": "sa", "partner": "sb", "c3d": "files/x.c3d",
                                   "videos": videos,
                                   "calibration": {c: "files/cal.json" for c in cams},
                                   "fps": 50.0}},
           "body_model": {"kind": "anny", "path": "files/m.npz"}}
    for path, value in edits.items():
        node = raw
        keys = path.split("__")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    p = tmp / "r.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def _run(argv, capsys):
    lines: list[str] = []
    code = cli.main(argv, log=lines.append)
    return code, "\n".join(lines) + capsys.readouterr().out


def test_schema_values_out_of_range_are_each_named(tmp_path, capsys):
    p = _recipe(tmp_path)
    raw = yaml.safe_load(p.read_text())
    raw["sequences"]["g/X 1"]["fps"] = -50
    raw["sequences"]["g/X 1"]["mocap"] = {"rate_hz": 0, "sync_offset_s": float("inf")}
    raw["ground_plane"] = {"normal": [0, 0, 3], "offset": 0}
    p.write_text(yaml.safe_dump(raw))
    code, out = _run(["release", "--recipe", str(p), "--outputs", str(tmp_path / "out")], capsys)
    assert code == 2
    for field in ("sequences.g/X 1.fps", "sequences.g/X 1.mocap.rate_hz",
                  "sequences.g/X 1.mocap.sync_offset_s", "ground_plane.normal"):
        assert f"{p}: {field}:" in out, (field, out)
    assert not (tmp_path / "out").exists()


def test_stage_options_and_video_problems_are_all_reported_before_anything_runs(tmp_path, capsys):
    p = _recipe(tmp_path, stages={"marker_fit": {"max_frames": -2, "weights": {"L_foo": 1.0}},
                                  "keypoints": {"stride": 0}})
    code, out = _run(["release", "--recipe", str(p), "--outputs", str(tmp_path / "out")], capsys)
    assert code == 2
    assert "nothing was run" in out
    assert f"{p}: stages.marker_fit" in out and "max_frames" in out
    assert f"{p}: stages.keypoints" in out and "stride" in out
    assert "v.mp4" in out  # the placeholder video can't be read: named by the video check
    assert not list((tmp_path / "out").rglob("manifest.json"))


def test_weights_name_unknown_terms(tmp_path, capsys):
    p = _recipe(tmp_path, stages={"marker_fit": {"weights": {"L_foo": 1.0}}})
    code, out = _run(["release", "--recipe", str(p), "--outputs", str(tmp_path / "out")], capsys)
    assert code == 2
    assert f"{p}: stages.marker_fit" in out and "L_foo" in out


def _video(path: Path, n: int, fps: float) -> str:
    from formats.video import write_mp4

    frames = np.zeros((n, 32, 32, 3), np.uint8)
    frames[:, 8:24, 8:24] = np.linspace(0, 255, n, dtype=np.uint8)[:, None, None, None]
    write_mp4(path, frames, fps)
    return str(path)


def test_check_videos_names_a_wrong_rate_not_a_short_view(tmp_path):
    from stages.common import check_videos

    ok = [_video(tmp_path / f"c{i}.mp4", 12, 50.0) for i in range(3)]
    assert check_videos(ok, 50.0) == []
    short = _video(tmp_path / "short.mp4", 2, 50.0)  # cut to the shortest: a warning, later
    assert check_videos(ok[:2] + [short], 50.0) == []
    msgs = check_videos(ok, 25.0)
    assert len(msgs) == 3 and all("fps: the video runs at 50 fps, the recipe says 25" in m for m in msgs)


def test_a_video_at_another_rate_stops_the_run_with_its_name(tmp_path, capsys):
    files = tmp_path / "files"
    files.mkdir(parents=True)
    vids = {"c1": _video(files / "c1.mp4", 12, 50.0), "c2": _video(files / "c2.mp4", 12, 50.0),
            "c3": _video(files / "c3.mp4", 12, 25.0)}
    p = _recipe(tmp_path, videos=vids)
    code, out = _run(["sequence", "g/X 1", "--recipe", str(p), "--outputs", str(tmp_path / "out")],
                     capsys)
    assert code == 2
    assert "c3.mp4: fps: the video runs at 25 fps" in out and f"{p}: sequences.g/X 1.videos" in out
    assert not list((tmp_path / "out").rglob("manifest.json"))


def test_every_layer_of_problems_comes_out_in_one_run(tmp_path, capsys):
    """Schema errors of several fields, a missing file, unknown and bad stage options, an unknown
    stage, a name too long and the video check: one run, one line each, exit 2, nothing written."""
    long_action = "A" * 300
    p = _recipe(tmp_path, stages={"marker_fit": {"max_frames": -2, "bogus": 1}, "nostage": {}})
    raw = yaml.safe_load(p.read_text())
    q = raw["sequences"]["g/X 1"]
    q["fps"] = "fast"  # schema: a field's value
    q["vidoes"] = {}  # schema: an unknown key
    raw["subjects"]["sb"]["sex"] = "other"  # schema: another entry
    raw["subjects"]["sa"]["scan"] = "files/none.ply"  # a missing file beside them
    raw["sequences"][f"g/{long_action}"] = {**{k: v for k, v in q.items() if k != "vidoes"},
                                            "fps": 50.0}
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    out_dir = tmp_path / "out"
    for command in (["release"], ["sequence", "g/X 1"], ["status"]):
        code, out = _run([*command, "--recipe", str(p), "--outputs", str(out_dir)], capsys)
        assert code == 2, (command, out)
        lines = [ln for ln in out.splitlines() if ln.startswith(f"{p}: ")]
        for want in ("sequences.g/X 1.fps: Input should be a valid number",
                     "sequences.g/X 1.vidoes: unknown key", "subjects.sb.sex: Input should be",
                     f"subjects.sa.scan: file not found: {tmp_path / 'files' / 'none.ply'}",
                     f"sequences.g/{long_action}: name too long",
                     "stages.marker_fit.bogus: unknown parameter", "stages.nostage: unknown stage",
                     "sequences.g/X 1.videos: "):
            assert sum(ln.startswith(f"{p}: {want}") for ln in lines) == 1, (command, want, out)
        assert any(ln.startswith(f"{p}: stages.marker_fit") and "max_frames" in ln
                   for ln in lines), out  # the bad value beside the unknown key of one stage
        assert sum("none.ply" in ln for ln in lines) == 1, out  # said once, not per stage
        assert len(lines) == len(set(lines)) == 9, out
        assert not out_dir.exists(), command  # not even the file-hash memo


def test_a_missing_file_is_named_once_and_the_run_stops(tmp_path, capsys):
    p = _recipe(tmp_path, videos={"c1": "files/v.mp4", "c2": "files/gone.mp4", "c3": "files/v.mp4"})
    code, out = _run(["sequence", "g/X 1", "--recipe", str(p), "--outputs", str(tmp_path / "o")],
                     capsys)
    assert code == 2
    gone = str(tmp_path / "files" / "gone.mp4")
    assert [ln for ln in out.splitlines() if gone in ln] == \
        [f"{p}: sequences.g/X 1.videos.c2: file not found: {gone}"], out
    assert "v.mp4" in out  # the other views are still checked
