"""Body models: arrays, LBS in numpy and CasADi, loaders, joint sets, regions, markers.

    from body import load_model, forward
    model = load_model("anny")
    out = forward(model, betas, body_pose, global_orient, transl)   # out.vertices (F, V, 3)
"""
from body.lbs import BodyOutput, RestState, forward, rest_state
from body.loaders import load_model
from body.model import BodyModel

__all__ = ["BodyModel", "BodyOutput", "RestState", "forward", "load_model", "rest_state"]
