"""The twin's files: its default campaign, the validation and second-station campaigns, and twin.json (its
truth: the errors, the noise floor, the misreads, the trackers' poses, the measured difficulty), written
by `generate` for `python -m pipeline.commands.twin` (byte for byte the committed data/raw, a test checks it)."""
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.project.config import write_json
from pipeline.lib.reading.campaigns import pair_sha256, write_pair
from pipeline.lib.robot.kinematics import GRAVITY
from pipeline.lib.sim.difficulty import difficulty
from pipeline.lib.sim.twin import (LINK_COM, LINK_MASS, MEAN_NORM_3D, RAW, REGIONS, SEED, STATION_B,
                                   TRACKER_SIGMA_MM, VALIDATION, ZERO_POSE_DEG, Twin, sample_errors)


def twin_record(twin: Twin, misreads: dict) -> dict:
    """The twin's truth for twin.json (everything but the measured difficulty)."""
    e = twin.errors
    return {
        "seed": twin.seed,
        "robot": "ur5",
        "errors": {k: np.asarray(v).round(12).tolist() for k, v in e.items()},
        "notes": ("commanded q -> actual q = q + gear(q) + (tau(q) - tau(zero_pose)) / stiffness "
                  "+ N(0, joint_sigma); marker = fk(true_geometry, actual q); tracker reading = "
                  "R marker + t + N(0, tracker_sigma) (+ misread offset)"),
        "true_geometry": {k: v.numpy().round(12).tolist() for k, v in twin.geometry.items()},
        "zero_pose_deg": ZERO_POSE_DEG,
        "gravity_m_s2": list(GRAVITY),
        "link_mass_kg": LINK_MASS.tolist(),
        "link_com_mm": LINK_COM.tolist(),
        "tracker_pose": {"R": twin.R.round(12).tolist(), "t": twin.t.round(9).tolist(),
                         "convention": "P_tracker = R @ p_base + t"},
        "misread_ids": sorted(misreads),
        "misreads": {k: np.round(v, 6).tolist() for k, v in misreads.items()},
    }


def generate(out_dir: Path | str = RAW, seed: int = SEED, params: dict | None = None, fine: bool = True) -> dict:
    """Write joints.csv, tracker.csv, validation/{joints,tracker}.csv and twin.json; with params,
    also measure the difficulty. fine=False: the twin without its joints' fine angular structure
    (as before issue 22; the other errors, poses and noise are the same draws)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    errors = sample_errors(seed)
    if not fine:
        errors["fine_amp_arcsec"] = np.zeros_like(errors["fine_amp_arcsec"])
    twin = Twin(seed, errors)
    joints, tracker, misreads = twin.campaign()
    files = write_pair(out_dir, joints, tracker)
    record = twin_record(twin, misreads)
    record["campaign_sha256"] = pair_sha256(files["joints"], files["tracker"])
    record["noise_floor_mm"] = round(twin.noise_floor_mm, 6)
    record["noise_floor_method"] = ("Monte Carlo: 64 drives of each campaign pose, stream "
                                    "'floor'; tracker-only analytic value 1.5958 * sigma")
    record["noise_floor_tracker_only_mm"] = MEAN_NORM_3D * TRACKER_SIGMA_MM
    for key, spec in (("validation", VALIDATION), ("station_b", STATION_B)):
        vj, vt, (R, t) = twin.validation_campaign(spec["seed"], spec["n"], spec["prefix"])
        pair = write_pair(out_dir / spec["dir"], vj, vt)
        record[key] = {"seed": spec["seed"], "n": spec["n"], "files": spec["dir"],
                       "regions": {k: REGIONS[k] for k in spec["n"]},
                       "tracker_pose": {"R": R.round(12).tolist(), "t": t.round(9).tolist()},
                       "campaign_sha256": pair_sha256(pair["joints"], pair["tracker"])}
    if params is not None:
        # measured from the files as written (rounded), as the pipeline will see them
        joints = pd.read_csv(out_dir / "joints.csv")
        tracker = pd.read_csv(out_dir / "tracker.csv")
        record["difficulty"] = difficulty(joints, tracker, params, twin)
    write_json(out_dir / "twin.json", record)
    return record
