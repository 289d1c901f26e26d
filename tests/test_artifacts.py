"""Typed artifacts: ShapeFit and BodyFit through a folder (and an engine artifact), and every
kind of bad file rejected with an ArtifactError naming the file, the field and the frame."""
from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from artifacts import REASON_CODE, ArtifactError, BodyFit, ShapeFit
from formats.errors import InputError
from pipeline.store import StoredArtifact, Writer


def _rot(rng, F):
    from body.rotations import rodrigues

    return rodrigues(rng.normal(0, 1.0, (F, 3)))


def shape_fit(rng, M=6, S=12) -> ShapeFit:
    bary = rng.uniform(0.05, 1, (M, 3))
    return ShapeFit(betas=rng.normal(size=S), marker_names=np.array([f"M{i}" for i in range(M)]),
                    marker_face=rng.integers(0, 1000, M), marker_bary=bary / bary.sum(1, keepdims=True),
                    marker_offset=np.full(M, 0.0095), shape_source="scan",
                    placement_source="refined")


def body_fit(rng, F=10, J=7, M=5) -> BodyFit:
    vis = rng.uniform(size=(F, M)) > 0.2
    res = np.where(vis, rng.uniform(0, 0.01, (F, M)), np.nan)
    reason = np.zeros(F, np.int8)
    reason[:2] = REASON_CODE["held_before_first_marker"]
    reason[6] = REASON_CODE["too_few_markers"]
    return BodyFit(body_pose=rng.normal(0, 0.3, (F, J, 3)), global_orient=_rot(rng, F),
                   transl=rng.normal(0, 1, (F, 3)), betas=rng.normal(size=8),
                   frames=np.arange(0, 2 * F, 2), valid=reason == 0, invalid_reason=reason,
                   marker_names=np.array([f"m{i}" for i in range(M)]), marker_residual_m=res,
                   marker_weight=np.where(vis, rng.uniform(0, 1, (F, M)), np.nan), visible=vis)


def _write(folder: Path, arrays: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "fit.npz", **arrays)
    return folder


def test_shape_fit_round_trip_through_a_folder_and_an_engine_artifact(tmp_path):
    sf = shape_fit(np.random.default_rng(0))
    path = sf.save(Writer(tmp_path))
    assert path == tmp_path / "shape.npz"
    for src in (tmp_path, path, StoredArtifact(dir=tmp_path, key="k", unit="s1", stage="shape_fit", manifest={})):
        got = ShapeFit.load(src)
        assert got.names == sf.names
        for f in ShapeFit.FIELDS:
            np.testing.assert_array_equal(getattr(got, f.name), getattr(sf, f.name))
    raw = np.load(path)
    assert str(raw["artifact_kind"]) == "shape_fit" and int(raw["artifact_version"]) == 1


def test_body_fit_round_trip_keeps_the_valid_mask_and_reasons(tmp_path):
    bf = body_fit(np.random.default_rng(1))
    bf.save(Writer(tmp_path))
    got = BodyFit.load(tmp_path)
    np.testing.assert_array_equal(got.valid, bf.valid)
    np.testing.assert_array_equal(got.invalid_reason, bf.invalid_reason)
    assert got.invalid_reason.dtype == np.int8
    from artifacts.body_fit import INVALID_REASONS

    want = {"fitted": 7, "held_before_first_marker": 2, "too_few_markers": 1}
    assert got.reasons() == {n: want.get(n, 0) for n in INVALID_REASONS}  # every reason named
    np.testing.assert_array_equal(np.isnan(got.marker_residual_m), np.isnan(bf.marker_residual_m))
    np.testing.assert_allclose(got.global_orient, bf.global_orient)
    assert INVALID_REASONS[0] == "fitted"


def test_body_fit_without_markers_is_a_valid_kind(tmp_path):
    bf = replace(body_fit(np.random.default_rng(2)), marker_names=None, marker_residual_m=None,
                 marker_weight=None, visible=None)
    bf.save(Writer(tmp_path))
    got = BodyFit.load(tmp_path)
    assert not got.has_markers and got.num_frames == 10
    assert "visible" not in np.load(tmp_path / "fit.npz").files


def _bad(tmp_path, change) -> str:
    arrays = body_fit(np.random.default_rng(3)).arrays()
    change(arrays)
    folder = _write(tmp_path / "a", arrays)
    with pytest.raises(ArtifactError) as e:
        BodyFit.load(folder)
    assert isinstance(e.value, InputError)
    assert str(folder / "fit.npz") in str(e.value)
    return str(e.value)


def test_missing_field_is_named(tmp_path):
    msg = _bad(tmp_path, lambda a: a.pop("transl"))
    assert re.search(r"fit\.npz: transl: missing", msg), msg
    msg = _bad(tmp_path, lambda a: a.pop("visible"))  # one marker field without the others
    assert re.search(r"fit\.npz: visible: missing while", msg), msg


def test_wrong_shape_is_named(tmp_path):
    def short(a):
        a["transl"] = a["transl"][:-1]

    msg = _bad(tmp_path, short)
    assert re.search(r"fit\.npz: transl: expected shape \(F 3\) with F = 10 .*got \(9, 3\)", msg), msg

    def flat(a):
        a["betas"] = a["betas"][None]

    assert re.search(r"betas: expected shape \(S\)", _bad(tmp_path, flat))

    def dtype(a):
        a["valid"] = a["valid"].astype(float)

    assert re.search(r"valid: dtype float64 is not bool", _bad(tmp_path, dtype))


def test_wrong_kind_or_version_is_named(tmp_path):
    def kind(a):
        a["artifact_kind"] = np.array("shape_fit")

    assert re.search(r"fit\.npz: artifact_kind: is 'shape_fit', expected 'body_fit'",
                     _bad(tmp_path, kind))

    def version(a):
        a["artifact_version"] = np.array(7)

    assert re.search(r"artifact_version: is 7, this code reads version 1",
                     _bad(tmp_path, version))
    assert re.search(r"artifact_kind: missing", _bad(tmp_path, lambda a: a.pop("artifact_kind")))


def test_non_orthonormal_rotation_names_the_frame(tmp_path):
    def skew(a):
        a["global_orient"] = a["global_orient"].copy()
        a["global_orient"][4] *= 1.01  # scaled: not orthonormal

    msg = _bad(tmp_path, skew)
    assert re.search(r"global_orient \[frame 4\]: not a rotation matrix", msg), msg

    def nearly(a):  # within 1e-6: accepted
        a["global_orient"] = a["global_orient"] * (1 + 1e-8)

    arrays = body_fit(np.random.default_rng(3)).arrays()
    nearly(arrays)
    BodyFit.load(_write(tmp_path / "ok", arrays))


def test_translation_in_millimetres_is_rejected(tmp_path):
    def mm(a):
        a["transl"] = a["transl"] * 1000 + np.array([0, 0, 900.0])

    msg = _bad(tmp_path, mm)
    assert re.search(r"transl \[frame 0\]: \|value\| .* not metres", msg), msg


def test_mask_and_reasons_must_agree(tmp_path):
    def flip(a):
        a["valid"] = a["valid"].copy()
        a["valid"][0] = True  # reason 1 there

    assert re.search(r"valid \[frame 0\]: is True but invalid_reason is 1 "
                     r"\(held_before_first_marker\)", _bad(tmp_path, flip))

    def code(a):
        a["invalid_reason"] = a["invalid_reason"].copy()
        a["invalid_reason"][3] = 9

    assert re.search(r"invalid_reason \[frame 3\]: unknown code 9", _bad(tmp_path, code))

    def seen(a):  # a residual where the marker was not visible
        a["marker_residual_m"] = np.nan_to_num(a["marker_residual_m"])

    assert "not visible" in _bad(tmp_path, seen)


def test_save_validates_first_and_writes_nothing(tmp_path):
    sf = shape_fit(np.random.default_rng(4))
    bad = replace(sf, marker_offset=sf.marker_offset * 1000)  # mm
    with pytest.raises(ArtifactError, match=r"shape\.npz: marker_offset: marker M0: 9\.5 >= 0\.1"):
        bad.save(Writer(tmp_path))
    assert not (tmp_path / "shape.npz").exists()
    with pytest.raises(ArtifactError, match=r"shape_source: 'guess' is not one of"):
        replace(sf, shape_source="guess").validate()
    b = sf.marker_bary.copy()
    b[2] = 0.5
    with pytest.raises(ArtifactError, match=r"marker_bary: marker M2: coordinates sum to 1\.5"):
        replace(sf, marker_bary=b).validate()
    with pytest.raises(ArtifactError, match=r"no shape\.npz"):
        ShapeFit.load(tmp_path)


# ------------------------------------------------------------ convert, qa, export, release


def smplx_fit(rng, P=2, F=4):
    from artifacts import SMPLXFit

    return SMPLXFit(transl=rng.normal(0, 1, (P, F, 3)), global_orient=_rot(rng, P * F).reshape(P, F, 3, 3),
                    body_pose=_rot(rng, P * F * 21).reshape(P, F, 21, 3, 3),
                    left_hand_pose=_rot(rng, P * F * 15).reshape(P, F, 15, 3, 3),
                    right_hand_pose=_rot(rng, P * F * 15).reshape(P, F, 15, 3, 3),
                    jaw_pose=_rot(rng, P * F).reshape(P, F, 3, 3),
                    leye_pose=_rot(rng, P * F).reshape(P, F, 3, 3),
                    reye_pose=_rot(rng, P * F).reshape(P, F, 3, 3),
                    betas=rng.normal(size=(P, 10)), expression=np.zeros((P, 10)),
                    frames=np.arange(0, 3 * F, 3), valid=np.ones((P, F), bool),
                    v2s_mm=rng.uniform(1, 5, (P, F)), subjects=np.array(["s1", "s2"][:P]))


def _raises(fn, file: str, field: str) -> str:
    """``fn()`` raises an ArtifactError (an InputError) naming ``file`` and ``field``."""
    with pytest.raises(ArtifactError) as e:
        fn()
    assert isinstance(e.value, InputError)
    msg = str(e.value)
    assert file in msg and e.value.field == field, msg
    return msg


def test_smplx_fit_round_trip_and_bad_files(tmp_path):
    from artifacts import SMPLXFit

    sm = smplx_fit(np.random.default_rng(5))
    sm.save(Writer(tmp_path))
    got = SMPLXFit.load(StoredArtifact(dir=tmp_path, key="k", unit="g/a", stage="convert", manifest={}))
    assert (got.num_persons, got.num_frames) == (2, 4) and got.subjects.tolist() == ["s1", "s2"]
    for f in SMPLXFit.FIELDS:
        if getattr(sm, f.name) is not None:
            np.testing.assert_array_equal(getattr(got, f.name), getattr(sm, f.name))
    assert set(got.params()) >= {"transl", "global_orient", "body_pose", "jaw_pose", "betas"}
    file = str(tmp_path / "smplx.npz")

    def rewrite(change):
        a = sm.arrays()
        change(a)
        np.savez(tmp_path / "smplx.npz", **a)
        return lambda: SMPLXFit.load(tmp_path)

    _raises(rewrite(lambda a: a.pop("valid")), file, "valid")  # missing
    msg = _raises(rewrite(lambda a: a.update(v2s_mm=a["v2s_mm"][:, :-1])), file, "v2s_mm")
    assert "F = 4" in msg  # a wrong shape, against the other per-frame arrays
    t = sm.transl.copy()
    t[1, 2, 0] = np.nan
    msg = _raises(rewrite(lambda a: a.update(transl=t)), file, "transl")
    assert "non-finite" in msg
    R = sm.body_pose.copy()
    R[1, 3, 5] *= 1.1
    msg = _raises(rewrite(lambda a: a.update(body_pose=R)), file, "body_pose")
    assert "[frame 3]" in msg and "person 1" in msg
    _raises(rewrite(lambda a: a.pop("right_hand_pose")), file, "right_hand_pose")  # hands together
    with pytest.raises(ArtifactError, match=r"smplx\.npz: transl .*not metres"):
        replace(sm, transl=sm.transl * 1000 + 500).save(Writer(tmp_path / "mm"))
    assert not (tmp_path / "mm" / "smplx.npz").exists()


def test_surface_correspondence_checks_indices_and_barycentrics(tmp_path):
    from artifacts import SurfaceCorrespondence

    rng = np.random.default_rng(6)

    def bary(n):
        b = rng.uniform(0.1, 1, (n, 3))
        return b / b.sum(1, keepdims=True)

    c = SurfaceCorrespondence(tgt_vert_face=rng.integers(0, 8, 12), tgt_vert_bary=bary(12),
                              src_vert_face=rng.integers(0, 6, 10), src_vert_bary=bary(10),
                              src_face_tgt_face=rng.integers(0, 6, 8),
                              tgt_face_src_face=rng.integers(0, 8, 6),
                              tgt_faces=rng.integers(0, 12, (6, 3)), src_faces=rng.integers(0, 10, (8, 3)))
    c.save(Writer(tmp_path))
    got = SurfaceCorrespondence.load(tmp_path / "correspondence.npz")
    np.testing.assert_array_equal(got.src_face_tgt_face, c.src_face_tgt_face)
    _raises(lambda: replace(c, src_face_tgt_face=c.src_face_tgt_face + 6).validate("c.npz"),
            "c.npz", "src_face_tgt_face")
    b = c.tgt_vert_bary.copy()
    b[3] = [0.5, 0.5, 0.5]
    _raises(lambda: replace(c, tgt_vert_bary=b).validate("c.npz"), "c.npz", "tgt_vert_bary")
    b[3] = np.nan
    assert "non-finite" in _raises(lambda: replace(c, tgt_vert_bary=b).validate("c.npz"),
                                   "c.npz", "tgt_vert_bary")


def conversion_report():
    from artifacts import ConversionReport
    from artifacts.smplx_fit import PersonConversion, TargetInfo

    return ConversionReport(sequence="g/a", target=TargetInfo("/x/SMPLX_NEUTRAL.npz", "ab" * 32,
                                                             "smplx", 10608, True, "stand-in"),
                            correspondence_key="k1", registered_now=True,
                            per_person=(PersonConversion("s1", 2.5, 4.0, 9.0, 4, 1),
                                        PersonConversion("s2", float("nan"), None, None, 4)),
                            fps_per_core=30.0, cpu_s=0.27, registration_cpu_s=1.5,
                            warnings=("w",))


def test_conversion_report_round_trip_and_bad_json(tmp_path):
    import json

    from artifacts import ConversionReport

    rep = conversion_report()
    rep.save(Writer(tmp_path))
    got = ConversionReport.load(tmp_path)
    assert got.per_person[0] == rep.per_person[0] and got.per_person[1].v2s_median_mm is None
    assert got.target == rep.target and got.warnings == ("w",) and got.cpu_s == 0.27
    assert got.figures()["per_person"][0]["v2s_median_mm"] == 2.5
    file = str(tmp_path / "report.json")
    good = json.loads((tmp_path / "report.json").read_text())

    def bad(change):
        d = json.loads(json.dumps(good))
        change(d)
        (tmp_path / "report.json").write_text(json.dumps(d))
        return lambda: ConversionReport.load(tmp_path)

    _raises(bad(lambda d: d["target"].pop("sha256")), file, "target.sha256")  # missing
    _raises(bad(lambda d: d.update(per_person={"s1": 1})), file, "per_person")  # wrong shape
    _raises(bad(lambda d: d["per_person"][0].update(frames="4")), file, "per_person[0].frames")
    msg = _raises(bad(lambda d: d.update(cpu_s=float("nan"))), file, "cpu_s")  # NaN
    assert "non-finite" in msg
    _raises(bad(lambda d: d.update(artifact_kind="qa_result")), file, "artifact_kind")
    _raises(bad(lambda d: d.update(artifact_version=9)), file, "artifact_version")
    _raises(lambda: replace(rep, cpu_s=float("inf")).save(Writer(tmp_path / "x")),
            str(tmp_path / "x" / "report.json"), "cpu_s")
    assert not (tmp_path / "x" / "report.json").exists()


def qa_result(folder: Path):
    """A QA result of 6 frames (frames 2, 3 flagged by m1: one span) and its files."""
    from artifacts import QAMetrics, QAResult
    from artifacts.qa import QAFiles, QASpan, QASummary

    frames = np.arange(10, 22, 2)
    values = np.array([[1.0, np.nan]] * 6)
    values[2:4, 0] = 9.0
    flagged = np.zeros((6, 1), bool)
    flagged[2:4, 0] = True
    (folder / "overlays").mkdir(parents=True, exist_ok=True)
    for n in ("report.html", "qa.png", "overlays/overlay_000014.png"):
        (folder / n).write_bytes(b"x")
    return QAResult(
        metrics=QAMetrics(frames=frames, names=np.array(["m1", "m2"]), values=values,
                          reasons=np.array(["m1"]), flagged=flagged),
        summary=QASummary(frames=6, flagged_frames=2, flagged_rate=2 / 6, spans=1,
                          per_reason={"m1": 2}, not_valid={"wearer": 0},
                          sync_offset_frames={"c1": 0, "c2": 2}, people=("wearer",),
                          metrics_s=0.5),
        spans=(QASpan(14, 16, ("m1",), 14, {"m1": 9.0}),),
        frame_reasons={14: ("m1",), 16: ("m1",)}, thresholds={"m1": 5.0}, units={"m1": "mm"},
        files=QAFiles(report="report.html", plot="qa.png",
                      overlays={14: "overlays/overlay_000014.png"}, span_frames=(14, 16)))


def test_qa_result_round_trip_and_bad_files(tmp_path):
    import json

    from artifacts import QAResult

    qa = qa_result(tmp_path)
    qa.save(Writer(tmp_path))
    got = QAResult.load(StoredArtifact(dir=tmp_path, key="k", unit="g/a", stage="qa", manifest={}))
    assert got.summary == qa.summary and got.spans == qa.spans and got.files == qa.files
    assert got.summary.out_of_sync == {"c2": 2} and got.files.thumbnail() == "overlays/overlay_000014.png"
    np.testing.assert_array_equal(got.metrics.flagged_by([12, 14, 15, 16], lambda r: r == "m1"),
                                  [False, True, False, True])
    assert got.span_list() == [(14, 16, ["m1"])]
    file = str(tmp_path / "flags.json")
    good = json.loads((tmp_path / "flags.json").read_text())

    def bad(change):
        d = json.loads(json.dumps(good))
        change(d)
        (tmp_path / "flags.json").write_text(json.dumps(d))
        return lambda: QAResult.load(tmp_path)

    _raises(bad(lambda d: d["summary"].pop("flagged_rate")), file, "summary.flagged_rate")
    _raises(bad(lambda d: d.update(spans={"start": 14})), file, "spans")  # wrong shape
    msg = _raises(bad(lambda d: d["summary"].update(metrics_s=float("nan"))), file, "summary.metrics_s")
    assert "non-finite" in msg
    # the summary must agree with qa.npz, and the listed files must be there
    _raises(bad(lambda d: d["summary"].update(flagged_frames=3)), file, "summary.flagged_frames")
    _raises(bad(lambda d: d["frames"].update({"12": ["m1"]})), file, "frames.12")
    _raises(bad(lambda d: d["files"]["overlays"].update({"16": "overlays/none.png"})), file,
            "files.overlays.16")
    _raises(bad(lambda d: d["files"].update(report="../x.html")), file, "files.report")
    (tmp_path / "flags.json").write_text(json.dumps(good))
    # qa.npz: a wrong shape, an infinite value
    a = qa.metrics.arrays()
    a["flagged"] = a["flagged"][:-1]
    np.savez(tmp_path / "qa.npz", **a)
    _raises(lambda: QAResult.load(tmp_path), str(tmp_path / "qa.npz"), "flagged")
    a = qa.metrics.arrays()
    a["values"] = a["values"].copy()
    a["values"][4, 0] = np.inf
    np.savez(tmp_path / "qa.npz", **a)
    assert "[frame 4]" in _raises(lambda: QAResult.load(tmp_path), str(tmp_path / "qa.npz"), "values")


def sequence_export(folder: Path):
    from artifacts import SequenceExport, SequenceFigures
    from artifacts.export import ContactNote

    files = ("g1/valid/Hug 1.json", "g1/joints3d_25/Hug 1.json",
             "g1/interaction_contact_signature.json")
    for f in files:
        (folder / f).parent.mkdir(parents=True, exist_ok=True)
        (folder / f).write_text("{}")
    fig = SequenceFigures(sequence="g1/Hug 1", subjects=("a", "b"),
                          marker_fit={"residual_mm": {"median": 1.5}},
                          partner_fit={"reprojection_px": {"median": 4.0}},
                          convert={"per_person": [{"subject": "a", "v2s_median_mm": 2.0},
                                                  {"subject": "b", "v2s_median_mm": None}]},
                          shape_source={"a": "scan"})
    return SequenceExport(
        sequence="g1/Hug 1", group="g1", action="Hug 1", persons=("a", "b"), model="anny",
        frames=3, first_frame=0, last_frame=4, video_fps=5.0, person_frames_not_valid=2,
        not_valid_by_reason=({"subject": "a", "fitted": 2, "too_few_markers": 1},
                             {"subject": "b", "fitted": 2, "poor_reprojection": 1}),
        cameras={"c1": {"source": "c1.json", "model": "h36m"}},
        contact=ContactNote("contact.json", "anny", 2, 1, 3, {"anny": 2, "smplx": 2, "ghum": 0},
                            {"moved_to_exported_frames": True}),
        absent={"text_annotations": "no text"}, files=files, valid_file=files[0],
        contact_file=files[2], figures=fig)


def test_sequence_export_round_trip_and_bad_files(tmp_path):
    import json

    from artifacts import SequenceExport

    ex = sequence_export(tmp_path)
    ex.save(Writer(tmp_path))
    got = SequenceExport.load(StoredArtifact(dir=tmp_path, key="k", unit="g1/Hug 1", stage="export",
                                             manifest={}))
    assert got.files == ex.files and got.contact == ex.contact and got.contact.event
    assert got.path(got.valid_file) == tmp_path / "g1" / "valid" / "Hug 1.json"
    assert got.figures.marker_residual_median_mm() == 1.5
    assert got.figures.v2s_median_mm() == [2.0, None] and got.text_file is None
    assert got.not_valid_by_reason == ex.not_valid_by_reason and got.video_fps == 5.0
    file = str(tmp_path / "export.json")
    good = json.loads((tmp_path / "export.json").read_text())

    def bad(change, name="export"):
        d = json.loads(json.dumps(good))
        change(d)
        (tmp_path / f"{name}.json").write_text(json.dumps(d))
        return lambda: SequenceExport.load(tmp_path)

    _raises(bad(lambda d: d.pop("valid_file")), file, "valid_file")  # missing
    _raises(bad(lambda d: d.update(files="g1/valid/Hug 1.json")), file, "files")  # wrong shape
    msg = _raises(bad(lambda d: d.update(video_fps=float("nan"))), file, "video_fps")  # NaN
    assert "non-finite" in msg
    _raises(bad(lambda d: d["files"].append("g1/smplx/Hug 1.json")), file, "files[3]")  # not there
    _raises(bad(lambda d: d.update(text_file="g1/text_annotations.json")), file, "text_file")
    _raises(bad(lambda d: d["contact"].pop("original_frames")), file, "contact.original_frames")
    (tmp_path / "export.json").write_text(json.dumps(good))
    fig = json.loads((tmp_path / "figures.json").read_text())
    fig["convert"]["per_person"][0]["v2s_median_mm"] = "2 mm"
    (tmp_path / "figures.json").write_text(json.dumps(fig))
    _raises(lambda: SequenceExport.load(tmp_path), str(tmp_path / "figures.json"),
            "convert.per_person[0].v2s_median_mm")


def test_release_round_trip_and_bad_files(tmp_path):
    import json

    from artifacts import Release

    sheet = {"session": "lab", "subjects": ["a"], "sequences": {"g/a": {"frames": 3, "persons": ["a"]}},
             "sequences_not_exported": [], "qa": None,
             "totals": {"sequences": 1, "frames": 3, "person_frames": 3,
                        "person_frames_not_valid": 1, "not_valid_by_reason": {"too_few_markers": 1}}}
    (tmp_path / "datasheet.json").write_text(json.dumps(sheet))
    for n in ("datasheet.md", "MANIFEST.sha256"):
        (tmp_path / n).write_text("x")
    rel = Release.of({"ok": True, "files_checked": 1, "files": {"g/joints3d_25/a.json": "r"},
                      "problems": []})
    rel.save(Writer(tmp_path))
    got = Release.load(StoredArtifact(dir=tmp_path, key="k", unit="session", stage="release", manifest={}))
    assert got.verified and got.require_verified() == tmp_path and got.root == tmp_path
    assert got.sheet.totals.person_frames_not_valid == 1 and got.sheet.subjects == ("a",)
    file = str(tmp_path / "verification.json")
    good = json.loads((tmp_path / "verification.json").read_text())

    def bad(change):
        d = json.loads(json.dumps(good))
        change(d)
        (tmp_path / "verification.json").write_text(json.dumps(d))
        return lambda: Release.load(tmp_path)

    _raises(bad(lambda d: d.pop("ok")), file, "ok")  # missing
    _raises(bad(lambda d: d.update(problems="none")), file, "problems")  # wrong shape
    _raises(bad(lambda d: d.update(files_checked=2)), file, "files_checked")
    _raises(bad(lambda d: d.update(manifest="MISSING")), file, "manifest")
    failed = bad(lambda d: d.update(ok=False, problems=["x.json: broken"]))()
    _raises(failed.require_verified, file, "ok")
    (tmp_path / "verification.json").write_text(json.dumps(good))
    sheet["totals"]["frames"] = float("nan")  # NaN where a count is required
    (tmp_path / "datasheet.json").write_text(json.dumps(sheet))
    _raises(lambda: Release.load(tmp_path), str(tmp_path / "datasheet.json"), "totals.frames")


def test_exists_in_finds_an_optional_file(tmp_path):
    sf = shape_fit(np.random.default_rng(7))
    assert not ShapeFit.exists_in(tmp_path)
    sf.save(Writer(tmp_path))
    assert ShapeFit.exists_in(tmp_path)
    assert ShapeFit.exists_in(StoredArtifact(dir=tmp_path, key="k", unit="s", stage="x", manifest={}))
