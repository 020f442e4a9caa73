"""The probe's measured orientation: rotation columns and rigid multi-marker targets -> unit quaternions.

Every orientation leaves the ingest as a unit quaternion (w, x, y, z), scalar first, w >= 0, of the
rotation R that maps probe-frame vectors to tracker-frame vectors (p_tracker = R p_probe + t). All
conversions are scipy's (scipy.spatial.transform.Rotation); nothing here re-derives them.

Rotation columns (`ingest.columns.orientation`, read as `ingest.orientation` says):
    euler       3 angles, `sequence` as scipy's Rotation.from_euler: upper case (XYZ) intrinsic
                (about the turning body's axes), lower case (xyz) extrinsic (about the fixed tracker
                axes); `angle_unit` deg or rad. Intrinsic XYZ = extrinsic zyx of the reversed angles.
                An angle beyond one turn (+-360 deg, +-2 pi rad) is a bad rotation (a lost decimal
                point); `unit_mismatch` says when the angles look like the other unit.
    quaternion  4 numbers, w x y z (`scalar_first: true`) or x y z w (false). A norm off 1 by more
                than NORM_TOL (relative) is a bad rotation, not normalised away.
    matrix      9 numbers, row-major r11 r12 r13 r21 ... r33. Rows not orthonormal within ORTHO_TOL
                (max |R Rᵀ - I|) or det < 0 (a reflection) is a bad rotation.

Rigid multi-marker targets (optical trackers export one row per marker): each pose's markers are fitted
by Kabsch (frames.kabsch) to the target's geometry {name: (3,)} in its own frame. The pose is that frame:
its origin (t) and its rotation (R). While a residual exceeds the limit, `fit_pose` removes the marker
whose leaving out fits the others best and refits; fewer than MIN_MARKERS left, or markers within ACROSS x
the limit of a line (a marker error within the limit could turn the pose about that line by more than
1/ACROSS rad), and the pose has no fit.
`estimate_geometry`: the geometry when none is given: the first pose holding every marker, centred on
its markers' centroid, then each marker's median position over all poses (of >= 3 markers) in that pose's
frame fitted to the first, centred again: one refinement. Its axes are the tracker's at that first pose,
its origin the markers' centroid. A marker off in one pose (or a pose whose labels are swapped) leaves the
median where the other poses put it; fit_pose then removes it there.
"""
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.lib.robot.frames import DegenerateFit, kabsch

KINDS = {"euler": 3, "quaternion": 4, "matrix": 9}     # kind -> number of columns
NORM_TOL = 1e-3              # a quaternion whose norm is off 1 by more (relative) is a bad rotation
ORTHO_TOL = 1e-3             # a matrix with max |R Rᵀ - I| above this is a bad rotation
MIN_MARKERS = 3              # a rigid fit needs three (non-collinear) markers
ACROSS = 10.0                # markers' RMS distance from their main axis, in fit limits, for a rotation about it
TURN = {"deg": 360.0, "rad": 2 * np.pi}   # no Euler angle any convention writes lies beyond one turn ...
TURN_SLACK = 1e-4            # ... (relative, for one written rounded)
PI_SLACK = 1e-3              # radians written rounded: +-pi to 3 decimals is 3.142
RAD_SPREAD = 1.0             # degrees all within +-pi that span more than this (57 deg as radians) are radians


def canonical(rot: Rotation) -> np.ndarray:
    """Rotations -> (n, 4) unit quaternions w, x, y, z with w >= 0."""
    return rot.as_quat(canonical=True, scalar_first=True).reshape(-1, 4)


def quaternion(R: np.ndarray) -> np.ndarray:
    """One rotation matrix (3, 3) -> its unit quaternion (4,) w, x, y, z with w >= 0."""
    return canonical(Rotation.from_matrix(R))[0]


def quaternion_problems(q: np.ndarray) -> list:
    """(n, 4) -> per row None, or (why it is not a unit quaternion (norm off 1 by > NORM_TOL), column 0)."""
    norm = np.linalg.norm(q, axis=1)
    return [None if abs(n - 1.0) <= NORM_TOL else (f"quaternion norm {n:.6g}, not 1 (tolerance {NORM_TOL:g})", 0)
            for n in norm]


def matrix_problems(M: np.ndarray) -> list:
    """(n, 3, 3) -> per row None, or (why it is not a rotation (not orthonormal, or a reflection), column 0)."""
    off = np.abs(M @ np.swapaxes(M, 1, 2) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(M)
    return [(f"not orthonormal: max |R Rᵀ - I| = {o:.3g} > {ORTHO_TOL:g}", 0) if o > ORTHO_TOL else
            (f"a reflection (det {d:.6g} < 0)", 0) if d < 0 else None for o, d in zip(off, det)]


def euler_problems(v: np.ndarray, unit: str) -> list:
    """(n, 3) angles in `unit` -> per row None, or (why not: an angle beyond one turn, that angle's column)."""
    turn, out = TURN[unit], []
    for row in v:
        k = int(np.argmax(np.abs(row)))
        out.append(None if abs(row[k]) <= turn * (1 + TURN_SLACK) else
                   (f"angle {k + 1} = {row[k]:.6g} is beyond one turn (+-{turn:.6g} {unit}): a lost decimal point?", k))
    return out


def unit_mismatch(v: np.ndarray, unit: str, min_rows: int) -> tuple | None:
    """Finite Euler angles (n, 3) read in `unit` -> (row or None, column, why) when they look like the other
    unit, else None. Radians: more than half the rows hold an angle beyond one turn (degrees). Degrees: with
    `min_rows` rows or more, every angle within +-pi while a column spans more than RAD_SPREAD (radians;
    a fixed orientation near the tracker's axes spans a fraction of a degree)."""
    a = np.abs(v)
    if unit == "rad":
        beyond = np.flatnonzero(a.max(axis=1) > TURN["rad"] * (1 + TURN_SLACK))
        if 2 * len(beyond) <= len(v):
            return None
        r = int(beyond[0])
        c = int(np.argmax(a[r]))
        return r, c, (f"{len(beyond)} of {len(v)} rows hold an Euler angle beyond +-2 pi (e.g. {v[r, c]:.6g}), "
                      "read as radians: these look like degrees; set ingest.orientation.angle_unit: deg")
    if len(v) < max(min_rows, 1) or a.max() > np.pi + PI_SLACK:
        return None
    spread = np.ptp(v, axis=0)
    c = int(np.argmax(spread))
    if spread[c] <= RAD_SPREAD:
        return None
    return None, c, (f"every Euler angle, read as degrees, lies within +-{np.pi:.4f} though one column spans "
                     f"{spread[c]:.3g}: these look like radians; set ingest.orientation.angle_unit: rad")


def read(v: np.ndarray, spec: dict) -> tuple[list, Rotation | None]:
    """Finite rotation columns (n, k) read as `spec` -> (per row None or (why it is no rotation, the column
    (0..k-1) it names), the rotations of the rows without a problem, None if there are none)."""
    if spec["kind"] == "euler":
        bad, make = euler_problems(v, spec["angle_unit"]), lambda x: Rotation.from_euler(
            spec["sequence"], x, degrees=spec["angle_unit"] == "deg")
    elif spec["kind"] == "quaternion":
        bad, make = quaternion_problems(v), lambda x: Rotation.from_quat(x, scalar_first=spec["scalar_first"])
    else:
        v = v.reshape(-1, 3, 3)
        bad, make = matrix_problems(v), Rotation.from_matrix
    good = np.array([b is None for b in bad], bool)
    return bad, make(v[good]) if good.any() else None


def rotations(values: np.ndarray, spec: dict) -> tuple[np.ndarray, list]:
    """Rotation columns (n, k) read as `spec` (the ingest.orientation section) -> (quaternions (n, 4),
    NaN where bad; per row None or (why it is a bad rotation, the column it names, 0..k-1)). Rows holding
    NaN give NaN, no problem (their cells are already a row problem)."""
    values = np.asarray(values, float).reshape(len(values), KINDS[spec["kind"]])
    out, problems = np.full((len(values), 4), np.nan), [None] * len(values)
    rows = np.flatnonzero(np.isfinite(values).all(axis=1))
    bad, rot = read(values[rows], spec)
    if rot is not None:
        out[[r for r, b in zip(rows, bad) if b is None]] = canonical(rot)
    for r, b in zip(rows, bad):
        problems[r] = b
    return out, problems


# -------------------------------------------------------------------- rigid multi-marker targets

@dataclass
class PoseFit:
    """One pose's fit to the target geometry: R, t (None: no fit), each marker's residual (file units)."""
    R: np.ndarray | None
    t: np.ndarray | None
    residual: dict = field(default_factory=dict)     # name -> residual of the markers kept
    removed: list = field(default_factory=list)      # [(name, residual when removed)], worst first
    why: str | None = None                           # no fit: why


def fit_pose(geometry: dict, points: dict, limit: float) -> PoseFit:
    """Fit a pose's markers {name: (3,)} to the geometry {name: (3,)} (every name in it): P = R G + t.
    While a residual exceeds `limit`, the marker whose leaving out fits the others best is removed (its
    residual: its distance from their fit) and the pose refitted (`left_out`)."""
    names, removed = list(points), []
    while True:
        if len(names) < MIN_MARKERS:
            return PoseFit(None, None, {}, removed, f"{len(names)} usable marker(s), need {MIN_MARKERS}")
        G = np.array([geometry[n] for n in names])
        P = np.array([points[n] for n in names])
        try:
            R, t = kabsch(G, P)
        except DegenerateFit:
            return PoseFit(None, None, {}, removed, f"markers {', '.join(names)} are collinear in the target")
        rho = across(G)
        if rho < ACROSS * limit:
            return PoseFit(None, None, {}, removed, f"markers {', '.join(names)} lie within {rho:.3g} mm of a line "
                           f"(need {ACROSS * limit:g} mm across it: {ACROSS:g} x target_residual_mm); the rotation "
                           "about it is not determined")
        res = np.linalg.norm(G @ R.T + t - P, axis=1)
        if res.max() <= limit:
            return PoseFit(R, t, dict(zip(names, res.tolist())), removed)
        k, off = left_out(G, P) if len(names) > MIN_MARKERS else (None, 0.0)
        if k is None:                                 # three markers (or no other fit): the worst one goes
            k, off = int(np.argmax(res)), float(res.max())
        removed.append((names.pop(k), off))


def left_out(G: np.ndarray, P: np.ndarray) -> tuple[int, float]:
    """The marker (index into G, P (n, 3)) whose leaving out fits the others best (the least worst residual),
    and its distance from their fit; (None, 0.0) where no such fit exists. The worst residual of the fit of
    all is not it: a marker far off pulls that fit towards itself and pushes good ones out."""
    best = (np.inf, None, 0.0)
    for k in range(len(G)):
        rest = np.arange(len(G)) != k
        try:
            R, t = kabsch(G[rest], P[rest])
        except DegenerateFit:
            continue
        worst = np.linalg.norm(G[rest] @ R.T + t - P[rest], axis=1).max()
        best = min(best, (worst, k, float(np.linalg.norm(G[k] @ R.T + t - P[k]))))
    return best[1], best[2]


def across(G: np.ndarray) -> float:
    """The markers' (n, 3) RMS distance from their main axis (the line through their centroid that fits them
    best). A marker error e turns a fit about that axis by about e / this."""
    s = np.linalg.svd(G - G.mean(0), compute_uv=False)
    return float(np.sqrt((s[1:] ** 2).sum() / len(G)))


def estimate_geometry(poses: list) -> dict:
    """The target's geometry {name: (3,)} from poses [{name: (3,)}] (module docstring); ValueError when
    no pose holds every marker."""
    names = list(dict.fromkeys(n for p in poses for n in p))
    first = next((p for p in poses if len(p) == len(names)), None)
    if first is None:
        raise ValueError(f"no pose holds all {len(names)} markers ({', '.join(names)})")
    g0 = centred({n: first[n] for n in names})
    if collinear(g0):
        raise ValueError(f"the {len(names)} markers ({', '.join(names)}) lie on a line")
    seen = {n: [] for n in names}
    for p in poses:
        common = [n for n in p if n in g0]
        if len(common) < MIN_MARKERS:
            continue
        try:
            R, t = kabsch(np.array([g0[n] for n in common]), np.array([p[n] for n in common]))
        except DegenerateFit:
            continue
        for n in common:
            seen[n].append(R.T @ (np.asarray(p[n]) - t))
    return centred({n: np.median(v, axis=0) for n, v in seen.items()})    # a mislabelled pose: an outlier


def centred(geometry: dict) -> dict:
    """The geometry moved so that its markers' centroid is the origin."""
    c = np.mean(list(geometry.values()), axis=0)
    return {n: np.asarray(p, float) - c for n, p in geometry.items()}


def geometry_problem(geometry: dict, poses: list, limit: float) -> str | None:
    """Why a given geometry {name: (3,)} does not fit the measured poses [{name: (3,)}], or None. Each pair of
    its markers: the median over the poses holding both of their measured distance (a misread marker moves a
    few poses, a wrong geometry every one) against the geometry's, off by more than `limit`: its unit (every
    pair off by one factor), a mistyped marker (in every pair that is off), or another target. Distances
    cannot see a mirror image: where they fit, most poses holding every marker fitted better by a reflection
    than within `limit` by a rotation (a geometry drawn in a left-handed frame; a planar target's mirror image
    is a turn of it, never seen). Pairs no pose holds are not judged."""
    names = list(geometry)
    G = {n: np.asarray(geometry[n], float) for n in names}
    pairs = []                                             # (a, b, given distance, measured median)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d = [np.linalg.norm(p[a] - p[b]) for p in poses if a in p and b in p]
            if d:
                pairs.append((a, b, float(np.linalg.norm(G[a] - G[b])), float(np.median(d))))
    off = [(a, b, g, m) for a, b, g, m in pairs if abs(m - g) > limit]
    if off:
        k = float(np.median([m / g for *_, g, m in pairs if g > 0] or [np.nan]))   # two markers typed alike: g 0
        worst = max(off, key=lambda x: abs(x[3] - x[2]))
        said = (f"{len(off)} of its {len(pairs)} marker pairs are farther apart or closer in the poses than in it "
                f"(the median over the poses holding both; {worst[0]}-{worst[1]} {worst[3]:.3f} mm measured, "
                f"{worst[2]:.3f} mm given; limit {limit:g} mm, ingest.target_residual_mm)")
        if abs(k - 1) > 0.01 and all(abs(m - k * g) <= limit for *_, g, m in pairs):
            return f"{said}: every one {k:.4g} times its own: given in another unit?"
        common = set(names).intersection(*({a, b} for a, b, *_ in off))
        if len(common) == 1 and len(off) > 1:
            return f"{said}: each of them holds marker {common.pop()!r}: its coordinates mistyped?"
        return f"{said}: the geometry of another target?"
    full = [np.array([p[n] for n in names]) for p in poses if all(n in p for n in names)]
    Gm = np.array([G[n] for n in names])

    def fit(P, proper):                                    # the fit's worst residual, mm
        R, t = kabsch(Gm, P, proper)
        return np.linalg.norm(Gm @ R.T + t - P, axis=1).max()

    mirrored = [fit(P, False) <= limit < fit(P, True) for P in full]
    if full and 2 * sum(mirrored) > len(full):
        return (f"its mirror image fits {sum(mirrored)} of the {len(full)} poses holding every marker within {limit:g} "
                "mm (ingest.target_residual_mm), a turn of it none: the geometry is mirrored (drawn in a "
                "left-handed frame, or one axis' sign flipped)")
    return None


def collinear(geometry: dict) -> bool:
    """True when the geometry's markers cannot fix a rotation (fewer than 3, or on a line)."""
    G = np.array(list(geometry.values()), float)
    if len(G) < MIN_MARKERS:
        return True
    s = np.linalg.svd(G - G.mean(0), compute_uv=False)
    return bool(s[1] <= 1e-9 * max(s[0], 1e-12))
