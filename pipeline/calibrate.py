"""Stage calibrate: classical kinematic calibration on the train split (lib/identify.py).

Starts from nominal DH with the frame stage's tool, identifies the groups in
`calibrate.params` (DH errors, parallel-axis tilts, tool, base correction)
by robust least squares, fixing what the data cannot tell apart. Writes
models/calibration.json (the geometry) and reports/calibration.json (the
identification report and the error per split, nominal vs calibrated).
"""
import numpy as np
import torch

from .lib.artifacts import CALIBRATED_GEOMETRY, CALIBRATION_JSON, load_points
from .lib.columns import JOINTS_DEG, MEAS, SPLITS
from .lib.config import load_params, logger, section, write_json
from .lib.geometry import theory_geometry
from .lib.identify import errors_3d, identify
from .lib.kinematics import DTYPE, fk, save_geometry

log = logger(__name__)


def run(params: dict) -> dict:
    section(params, "robot")
    cfg = section(params, "calibrate")
    pts = load_points()
    q = np.radians(pts[JOINTS_DEG].to_numpy())
    p = pts[MEAS].to_numpy()
    train = (pts["split"] == "train").to_numpy()
    g0 = theory_geometry(params)[1]
    geometry, report = identify(q[train], p[train], g0, cfg)
    qt = torch.as_tensor(q, dtype=DTYPE)
    with torch.no_grad():
        p_cal, p_nom = fk(qt, geometry).numpy(), fk(qt, g0).numpy()
    report["splits"] = {
        s: {"n": int(m.sum()), "calibrated": errors_3d(p_cal[m], p[m]), "nominal": errors_3d(p_nom[m], p[m])}
        for s in SPLITS if (m := (pts["split"] == s).to_numpy()).any()}
    save_geometry(CALIBRATED_GEOMETRY, geometry, {"robot": params["robot"]["model"],
                                                "identified": report["identified"]})
    write_json(CALIBRATION_JSON, report)
    sp = report["splits"]
    last = sp.get("test", sp["train"])
    log.info("identified %d of %d parameters (fixed %s) in %.1f s, %d evaluations; cond %.3g; "
             "mean 3D error train %.4f -> %.4f mm, test %.4f -> %.4f mm",
             len(report["identified"]), report["n_candidates"], sorted(report["fixed"]),
             report["seconds"], report["nfev"], report["condition_number"],
             sp["train"]["nominal"]["mean_mm"], sp["train"]["calibrated"]["mean_mm"],
             last["nominal"]["mean_mm"], last["calibrated"]["mean_mm"])
    return report


if __name__ == "__main__":
    run(load_params())
