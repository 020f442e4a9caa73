"""How hard a campaign is, measured the pipeline's way (twin.json's `difficulty`): the nominal DH error after
a robust frame fit, and a classical calibration's error on the split's points (and, for the twin, against
its noise-free truth)."""
import numpy as np
import pandas as pd
import torch

from pipeline.lib.learning.splits import split_indices
from pipeline.lib.project.columns import JOINTS_DEG
from pipeline.lib.robot.frames import robust_kabsch
from pipeline.lib.robot.identify import identify
from pipeline.lib.robot.kinematics import DTYPE, fk, nominal_geometry
from pipeline.lib.sim.twin import Twin, ur5


def difficulty(joints: pd.DataFrame, tracker: pd.DataFrame, params: dict,
               twin: Twin | None = None) -> dict:
    """How hard the campaign is, measured the pipeline's way.

    1. robust Kabsch frame (eqs. 20-26) of nominal DH (tool 0) on the tracker points;
    2. nominal DH error after that frame (mean 3D, inliers);
    3. classical calibration (identify.identify, params' groups: elasto-geometric by
       default) on the SPEC split's train points; its mean 3D error on train/val/test, and
       vs the noise-free truth; the same without the compliance group (rigid).
    """
    q_deg = joints[JOINTS_DEG].to_numpy()
    P = tracker[["X", "Y", "Z"]].to_numpy()
    with torch.no_grad():
        q = torch.as_tensor(np.radians(q_deg), dtype=DTYPE)
        theory = fk(q, nominal_geometry(ur5())).numpy()
    R, t, inl, _ = robust_kabsch(theory, P, params["frame"]["outlier_k"],
                                 params["frame"]["outlier_min_mm"])
    meas = (P - t) @ R                                               # base frame
    e_nom = np.linalg.norm(meas - theory, axis=1)[inl]
    keep = np.flatnonzero(inl)
    idx = split_indices(len(keep), params["split"]["fractions"], params["split"]["seed"])
    train = keep[idx["train"]]
    cfg = params["calibrate"]
    geo, rep = identify(q[train], meas[train], nominal_geometry(ur5()), cfg)
    rigid, _ = identify(q[train], meas[train], nominal_geometry(ur5()),
                        {**cfg, "params": [p for p in cfg["params"] if p != "compliance"]})
    with torch.no_grad():
        e_cal = np.linalg.norm(fk(q, geo).numpy() - meas, axis=1)
        e_rigid = np.linalg.norm(fk(q, rigid).numpy() - meas, axis=1)
    out = {
        "frame_outliers": joints["point_id"][~inl].tolist(),
        "nominal_after_frame_mean_mm": float(e_nom.mean()),
        "nominal_after_frame_rms_mm": float(np.sqrt((e_nom ** 2).mean())),
        "nominal_after_frame_max_mm": float(e_nom.max()),
        "classical_fit_mean_mm": {k: float(e_cal[keep[v]].mean()) for k, v in idx.items()},
        "rigid_fit_mean_mm": {k: float(e_rigid[keep[v]].mean()) for k, v in idx.items()},
        "classical_fit_identified": rep["identified"],
        "classical_fit_fixed": sorted(rep["fixed"]),
    }
    if twin is not None:       # model error alone: calibrated FK vs the noise-free truth
        truth_base = (twin.to_tracker(twin.expected_position(q_deg)) - t) @ R
        with torch.no_grad():
            truth = np.linalg.norm(fk(q, geo).numpy() - truth_base, axis=1)
        out["classical_fit_vs_truth_mean_mm"] = float(truth[keep].mean())
    return out
