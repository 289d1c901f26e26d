"""The CHI3D benchmark evaluator: ``python -m evaluate PRED GT [--json OUT]``.

``evaluate.metrics`` the pure metric functions, ``evaluate.folders`` the CHI3D-layout reading,
``evaluate.protocol`` matching, masks and averaging, ``evaluate.__main__`` the CLI.
"""
from evaluate.folders import load_pairs
from evaluate.metrics import (
    box_iou,
    boxes_from_points,
    match_people,
    mpjpe,
    mpvpe,
    pa_mpjpe,
    pa_mpvpe,
    reorder_people,
    similarity_procrustes,
    translation_error,
)
from evaluate.protocol import evaluate_pairs, markdown


def evaluate_folders(pred_root, gt_root, smplx_model=None, anny_model=None) -> dict:
    """Score PRED against GT (both CHI3D-layout roots); raises the first InputError met.
    smplx_model / anny_model: model files for ``smplx/`` / ``anny/`` parameter files (None:
    ``$SMPLX_MODEL_PATH`` / the default Anny model)."""
    pairs, errors = load_pairs(pred_root, gt_root, smplx_model, anny_model)
    if errors:
        raise errors[0]
    result = evaluate_pairs(pairs)
    result["pred"], result["gt"] = str(pred_root), str(gt_root)
    return result


__all__ = ["box_iou", "boxes_from_points", "evaluate_folders", "evaluate_pairs", "load_pairs",
           "markdown", "match_people", "mpjpe", "mpvpe", "pa_mpjpe", "pa_mpvpe",
           "reorder_people", "similarity_procrustes", "translation_error"]
