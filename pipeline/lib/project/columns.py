"""Column names: the one source for every table the stages pass along (docs/data-format.md)."""

JOINTS_DEG = [f"j{i}_deg" for i in range(1, 7)]          # recorded joint angles, degrees
MEAS = ["meas_x", "meas_y", "meas_z"]                     # measured marker position, mm
MEAS_Q = ["meas_qw", "meas_qx", "meas_qy", "meas_qz"]     # measured probe orientation (unit quaternion, scalar
                                                          # first; tracker frame in ingest, base frame from theory on)
THEORY = ["theory_x", "theory_y", "theory_z"]             # nominal DH + tool, base frame, mm
ERR = ["err_x", "err_y", "err_z"]                         # meas - theory, base frame, mm
PRED = ["pred_x", "pred_y", "pred_z"]                     # model prediction, base frame, mm
AXES = ["x", "y", "z"]
CAMPAIGN, STATION = "campaign", "station"                 # each point's campaign and tracker station

# reports/compensation.csv (docs/data-format.md: names are a contract)
DJ_DEG = [f"dj{i}_deg" for i in range(1, 7)]
JCOMP_DEG = [f"j{i}_comp_deg" for i in range(1, 7)]
TARGET = ["target_x", "target_y", "target_z"]
COMPENSATION = (["point_id"] + JOINTS_DEG + DJ_DEG + JCOMP_DEG + TARGET + PRED
                + ["residual_mm", "iterations", "converged", "uncertainty_mm", "in_workspace",
                   "orientation_residual_arcsec"])
RANDOM_SPLITS = ("train", "val", "test")                  # the 8:1:1 split
SPLITS = RANDOM_SPLITS + ("holdout",)                      # values of the split column (holdout: split.holdout)
