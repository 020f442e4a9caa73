"""Classical elasto-geometric calibration: identify the geometry (the baseline the network must beat).

Identifies small corrections to the geometry (pipeline.lib.robot.kinematics) from
measured positions in the base frame:
    d, a, alpha, offset   per joint (standard DH, eq. 1)
    beta                  Ry tilt of the parallel axes (`tilt_joints`)
    tool                  marker offset in the flange frame
    tool_rot              the probe's rotation in the flange frame (where orientation is measured)
    base                  base-frame correction [rx, ry, rz, tx, ty, tz]
    compliance            joint compliance under the links' gravity torques (kinematics.deflected):
                          the configuration-dependent sag of the arm, reported also as stiffness
    <station>_rx..tz      with several tracker stations: each further station's frame, relative to
                          the first's (its points are measured as D_s(base(chain(q)))); identified
                          jointly with the robot, so one geometry explains every station
    <station>_tool_x..z   with a tool per station (frame.tool_per_station): each further station's
                          tool minus the first's, started at the frame stage's estimate
Where the campaign measures the probe's orientation, each pose gives six residuals: position (mm)
and orientation (rad, rotation_error), weighted by their noises (`calibrate.pose_noise`: the
orientation rows in mm-equivalents, noise_mm / noise_rad), so joint 6's angle and the wrist's
tilts, invisible to a marker on the last axis, become identifiable.
Solved by robust trust-region least squares (scipy `least_squares`, Jacobian from
torch autograd of `fk`). Before solving, parameters the data cannot tell
apart are found by column-pivoted QR of the column-scaled Jacobian and kept
at nominal (delta 0): e.g. d1 vs base tz, offset1 vs base rz, d2/d3/d4 on
the parallel axes; compliance of joint 1 (its axis is vertical: no gravity torque) and of
joint 6 (the flange's centre of mass lies on its axis).

The identified geometry is written and read back by kinematics.save_geometry / load_geometry.
"""
import time

import numpy as np
import scipy.linalg
import torch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pipeline.lib.project.config import CALIBRATION_GROUPS as GROUPS       # declared with the settings' rules
from pipeline.lib.robot.kinematics import DTYPE, RIGID_KEYS, TOOL_ROT, fk, fk_pose, rigid_xyz, rotation_error
ARCSEC = np.pi / (180 * 3600)
BASE_NAMES = ["rx", "ry", "rz", "tx", "ty", "tz"]
TOOL_NAMES = ["x", "y", "z"]


# ----------------------------------------------------------------------------- parameters

def parameter_spec(cfg: dict) -> list[tuple[str, str, int]]:
    """(name, geometry key, index) of every candidate parameter, in cfg["params"] order."""
    spec = []
    for grp in cfg["params"]:
        if grp not in GROUPS:
            raise ValueError(f"params.yaml calibrate.params: unknown group {grp!r}; use {GROUPS}")
        if grp in ("d", "a", "alpha", "offset"):
            spec += [(f"{grp}{j + 1}", grp, j) for j in range(6)]
        elif grp == "compliance":
            spec += [(f"c{j + 1}", grp, j) for j in range(6)]
        elif grp == "beta":
            spec += [(f"beta{j}", "beta", j - 1) for j in cfg["tilt_joints"]]      # 1-6: config.RULES
        elif grp == "tool":
            spec += [(f"tool_{c}", "tool", i) for i, c in enumerate(TOOL_NAMES)]
        elif grp == "tool_rot":
            spec += [(f"tool_r{c}", TOOL_ROT, i) for i, c in enumerate(TOOL_NAMES)]
        else:
            spec += [(f"base_{c}", "base", i) for i, c in enumerate(BASE_NAMES)]
    return spec


def is_angular(key: str, index: int) -> bool:
    """Angles are rad internally and reported in degrees (compliance in deg/(N·m)); lengths in mm."""
    return key in ("alpha", "offset", "beta", "compliance", TOOL_ROT) or (key in ("base", "station") and index % 6 < 3)


def station_spec(stations: list[str], tools: bool = False) -> list[tuple[str, str, int]]:
    """The frame correction of every station but the first: 6 parameters each, key "station"
    (tools: and its tool offset relative to the first's, 3 each, key "station_tool")."""
    return ([(f"{s}_{c}", "station", 6 * k + i) for k, s in enumerate(stations) if k > 0
             for i, c in enumerate(BASE_NAMES)]
            + [(f"{s}_tool_{c}", "station_tool", 3 * k + i) for k, s in enumerate(stations) if tools and k > 0
               for i, c in enumerate(TOOL_NAMES)])


def selectors(spec, n_stations: int = 1) -> dict:
    """Per geometry key (and "station", "station_tool"), a (size, P) 0/1 matrix placing the
    parameter vector's deltas."""
    sizes = {"d": 6, "a": 6, "alpha": 6, "offset": 6, "beta": 6, "tool": 3, "base": 6, "compliance": 6, TOOL_ROT: 3,
             "station": 6 * n_stations, "station_tool": 3 * n_stations}
    S = {k: torch.zeros(n, len(spec), dtype=DTYPE) for k, n in sizes.items()}
    for p, (_, key, i) in enumerate(spec):
        S[key][i, p] = 1.0
    return S


def apply_deltas(x: torch.Tensor, g0: dict, S: dict) -> dict:
    """Geometry g0 (its rigid keys) + deltas x (mm / rad), differentiable in x (masses are never identified).
    A tool_rot delta on a geometry without one starts from the identity."""
    g0 = {**g0, TOOL_ROT: g0.get(TOOL_ROT, torch.zeros(3, dtype=DTYPE))} if TOOL_ROT in S and TOOL_ROT not in g0 \
        and bool(S[TOOL_ROT].any()) else g0
    return {k: g0[k] + S[k] @ x if k in S else g0[k] for k in RIGID_KEYS if k in g0}


def rigid(geometry: dict) -> dict:
    """The rigid keys of a geometry as float64 tensors (its error maps left out)."""
    return {k: torch.as_tensor(geometry[k], dtype=DTYPE) for k in RIGID_KEYS if k in geometry}


def orientation_weight(noise: dict) -> float:
    """mm per rad: the orientation rows' weight, `calibrate.pose_noise` {mm, arcsec} (noise_mm / noise_rad)."""
    return noise["mm"] / (noise["arcsec"] * ARCSEC)


def station_tools(x: torch.Tensor, S: dict, tools0: torch.Tensor | None) -> torch.Tensor:
    """Each station's tool minus the first's, (S, 3) mm: the start tools0 (zeros if None) + deltas."""
    d = (S["station_tool"] @ x).reshape(-1, 3)
    return d if tools0 is None else d + tools0


def predicted(q: torch.Tensor, x: torch.Tensor, g0: dict, S: dict, station: torch.Tensor | None,
              tools0: torch.Tensor | None = None, orientation: bool = False):
    """Measured-pose model: fk of g0 + deltas (with each point's station tool), then each point's
    station correction: positions (n, 3) mm and, with orientation, the probe's rotations (n, 3, 3) (else None)."""
    g = apply_deltas(x, g0, S)
    if station is not None:
        g = {**g, "tool": g["tool"] + station_tools(x, S, tools0)[station]}   # tool (n, 3)
    p, R = fk_pose(q, g) if orientation else (fk(q, g), None)
    if station is None:
        return p, R
    Rs, t = rigid_xyz((S["station"] @ x).reshape(-1, 6))                   # (S, 3, 3), (S, 3)
    p = torch.einsum("nij,nj->ni", Rs[station], p) + t[station]
    return p, (None if R is None else Rs[station] @ R)


def positions(q, x, g0, S, station, tools0=None) -> torch.Tensor:
    """The measured-position model (n, 3) mm (predicted without orientation)."""
    return predicted(q, x, g0, S, station, tools0)[0]


def residual_rows(q, x, g0, S, station, tools0, p_meas: torch.Tensor, R_meas: torch.Tensor | None,
                  weight: float) -> torch.Tensor:
    """Model minus measurement per pose: (n, 3) mm, or with measured orientations R_meas (n, 3, 3)
    (n, 6): position, then weight (mm/rad) times the rotation error."""
    p, R = predicted(q, x, g0, S, station, tools0, R_meas is not None)
    if R_meas is None:
        return p - p_meas
    return torch.cat([p - p_meas, weight * rotation_error(R, R_meas)], 1)


def jacobian(q, x, g0, S, station=None, tools0=None, p_meas=None, R_meas=None, weight=1.0) -> torch.Tensor:
    """d residual_rows / d x, flattened: (3n or 6n, P), by forward-mode autograd (P << 3n); p_meas does not
    enter it (None: zeros)."""
    p_meas = torch.zeros(len(q), 3, dtype=DTYPE) if p_meas is None else p_meas
    return torch.func.jacfwd(lambda v: residual_rows(q, v, g0, S, station, tools0, p_meas, R_meas,
                                                     weight).reshape(-1))(x)


def geometry_jacobian(q: torch.Tensor, geometry: dict, cfg: dict, names: list[str] | None = None,
                      weight: float | None = None):
    """d (positions, and with weight (mm/rad) the weighted probe orientation) / d the candidate parameters of
    the `calibrate:` section's groups (those in `names`, default all), at `geometry` (its error maps, if any,
    kept in the chain): (3n or 6n, P), rows per pose as residual_rows', and the parameters' spec."""
    spec = [s for s in parameter_spec(cfg) if names is None or s[0] in names]
    maps = {k: v for k, v in geometry.items() if k not in RIGID_KEYS}
    g0, S = rigid(geometry), selectors(spec)

    def rows(v):
        g = {**apply_deltas(v, g0, S), **maps}
        if weight is None:
            return fk(q, g).reshape(-1)
        p, R = fk_pose(q, g)
        return torch.cat([p, weight * rotation_error(R, R.detach())], 1).reshape(-1)
    J = torch.func.jacfwd(rows)(torch.zeros(len(spec), dtype=DTYPE))
    return J.numpy(), spec


def corrected(geometry: dict, spec: list, dx: np.ndarray) -> dict:
    """geometry with the parameter corrections dx (in `spec`'s units: mm, rad) added."""
    maps = {k: v for k, v in geometry.items() if k not in RIGID_KEYS}
    g0 = rigid(geometry)
    return {**apply_deltas(torch.as_tensor(dx, dtype=DTYPE), g0, selectors(spec)), **maps}


def in_units(spec: list, dx: np.ndarray) -> dict:
    """{name: value} of parameter corrections in report units: deg (angles; compliance deg/(N·m)) or mm."""
    return {name: float(v * (np.degrees(1.0) if is_angular(key, i) else 1.0)) for (name, key, i), v in zip(spec, dx)}


# ----------------------------------------------------------------------------- identifiability

def identifiability(J: np.ndarray, names: list[str], rank_tol: float) -> dict:
    """Which parameters the data can identify (column-pivoted QR of the scaled Jacobian).

    Columns are scaled to unit norm (mm and rad become comparable); a parameter
    whose pivot |R_kk| falls below rank_tol * |R_00| is fixed at nominal. Exact
    ties (truly redundant pairs) go to the earlier group of cfg["params"]
    (a 1e-7 relative bias). The reason names the kept parameters that absorb it.
    """
    norms = np.linalg.norm(J, axis=0)
    P = len(names)
    dead = norms <= 1e-12 * max(norms.max(), 1e-300)
    Js = J / np.where(dead, 1.0, norms)
    Js *= 1.0 + 1e-7 * (P - np.arange(P)) / P                     # tie-break by priority
    Js[:, dead] = 0.0
    _, Rq, piv = scipy.linalg.qr(Js, mode="economic", pivoting=True)
    diag = np.abs(np.diag(Rq))
    rank = int((diag > rank_tol * diag[0]).sum())
    keep = np.zeros(P, bool)
    keep[piv[:rank]] = True
    fixed = {}
    Jk = Js[:, keep]
    kept_names = [n for n, k in zip(names, keep) if k]
    for j in np.flatnonzero(~keep):
        if dead[j]:
            fixed[names[j]] = "no effect on the measured positions (zero Jacobian column)"
            continue
        coef, *_ = np.linalg.lstsq(Jk, Js[:, j], rcond=None)
        rel = np.linalg.norm(Jk @ coef - Js[:, j])
        big = np.argsort(-np.abs(coef))[:3]
        partners = [f"{coef[b]:+.3g}·{kept_names[b]}" for b in big if abs(coef[b]) > 1e-3]
        fixed[names[j]] = (f"redundant: its scaled Jacobian column = {' '.join(partners)} "
                           f"(relative residual {rel:.1e}, pivot below rank_tol {rank_tol:g})")
    s = np.linalg.svd(Js[:, keep] / np.linalg.norm(Js[:, keep], axis=0), compute_uv=False)
    return {"keep": keep, "fixed": fixed, "rank": rank,
            "condition": float(s[0] / s[-1]), "pivots": diag.tolist()}


# ----------------------------------------------------------------------------- identification

def errors_3d(p: np.ndarray, p_meas: np.ndarray) -> dict:
    e = np.linalg.norm(p - p_meas, axis=1)
    return {"mean_mm": float(e.mean()), "rms_mm": float(np.sqrt((e ** 2).mean())),
            "max_mm": float(e.max())}


def orientation_angles(R: np.ndarray, R_meas: np.ndarray) -> np.ndarray:
    """The angle (n,) arcsec between predicted and measured orientations (n, 3, 3) x2."""
    return Rotation.from_matrix(np.einsum("nji,njk->nik", R, R_meas)).magnitude() / ARCSEC   # exact near 0 (arccos is not)


def orientation_errors(R: np.ndarray, R_meas: np.ndarray) -> dict:
    """The angle between predicted and measured orientations (n, 3, 3) x2, arcsec: mean, rms, p95, max."""
    e = orientation_angles(R, R_meas)
    return {"mean_arcsec": float(e.mean()), "rms_arcsec": float(np.sqrt((e ** 2).mean())),
            "p95_arcsec": float(np.percentile(e, 95)), "max_arcsec": float(e.max())}


def identify(q: torch.Tensor | np.ndarray, p_meas: np.ndarray, geometry0: dict, cfg: dict,
             station: np.ndarray | None = None, stations: list[str] | None = None,
             station_tools0: np.ndarray | None = None, R_meas: np.ndarray | None = None):
    """Identify geometry corrections from joint angles q (n, 6) rad and positions p_meas (n, 3) mm
    (and, where measured, the probe's orientations R_meas (n, 3, 3) in the base frame).

    With several tracker stations, station (n,) indexes `stations` (the first is the base frame
    the geometry lives in) and each further station's frame correction is identified jointly;
    with station_tools0 (S, 3) mm, each station's own tool minus the first's (a tool per
    station), those offsets too, started there. The tool_rot group is a candidate only with R_meas.
    Returns (geometry dict of tensors, report dict); report["stations"] holds the corrections,
    report["station_tools"] the tool offsets (zeros: the tool is shared).
    cfg: the `calibrate:` section (params, tilt_joints, loss, loss_scale_mm, pose_noise, rank_tol, tol, max_nfev).
    """
    t0 = time.perf_counter()
    q = torch.as_tensor(np.asarray(q, float), dtype=DTYPE)
    p_meas = np.asarray(p_meas, float)
    p_t = torch.as_tensor(p_meas, dtype=DTYPE)
    R_t = None if R_meas is None else torch.as_tensor(np.asarray(R_meas, float), dtype=DTYPE)
    weight = orientation_weight(cfg["pose_noise"])
    g0 = rigid(geometry0)
    stations = stations or ["main"]
    station = None if len(stations) == 1 else torch.as_tensor(np.asarray(station), dtype=torch.long)
    tools0 = None if station_tools0 is None else torch.as_tensor(np.asarray(station_tools0, float), dtype=DTYPE)
    robot_spec = [s for s in parameter_spec(cfg) if R_meas is not None or s[1] != TOOL_ROT]
    spec = robot_spec + station_spec(stations, tools0 is not None)
    names = [s[0] for s in spec]
    S = selectors(spec, len(stations))
    P = len(spec)
    x0 = torch.zeros(P, dtype=DTYPE)
    rows = lambda x: residual_rows(q, x, g0, S, station, tools0, p_t, R_t, weight)

    J0 = jacobian(q, x0, g0, S, station, tools0, p_t, R_t, weight).numpy()
    ident = identifiability(J0, names, cfg["rank_tol"])
    keep = ident["keep"]
    fixed_by_stations = {}
    if station is not None:       # what the free station frames cost: robot parameters fixed only with them
        alone = identifiability(J0[:, :len(robot_spec)], names[:len(robot_spec)], cfg["rank_tol"])["fixed"]
        fixed_by_stations = {n: why for n, why in ident["fixed"].items() if n not in alone}
    scale = 1.0 / np.linalg.norm(J0[:, keep], axis=0)        # x_scale: unit-norm columns

    def full(xk):
        x = np.zeros(P)
        x[keep] = xk
        return torch.as_tensor(x, dtype=DTYPE)

    def residuals(xk):
        with torch.no_grad():
            return rows(full(xk)).numpy().ravel()

    def jac(xk):
        return jacobian(q, full(xk), g0, S, station, tools0, p_t, R_t, weight).numpy()[:, keep]

    tol = cfg["tol"]
    sol = least_squares(residuals, np.zeros(keep.sum()), jac=jac, method="trf",
                        loss=cfg["loss"], f_scale=cfg["loss_scale_mm"],
                        x_scale=scale, ftol=tol, xtol=tol, gtol=tol,
                        max_nfev=cfg["max_nfev"])
    x = full(sol.x)
    geometry = {k: v.detach() for k, v in apply_deltas(x, g0, S).items()}

    # standard errors: sigma^2 (J^T J)^-1 at the solution (plain least-squares residuals)
    r = residuals(sol.x)
    Jk = jac(sol.x)
    dof = max(len(r) - keep.sum(), 1)
    sigma2 = float(r @ r / dof)
    cov = sigma2 * np.linalg.pinv(Jk.T @ Jk)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))

    estimates = {}
    for k, (name, key, i) in enumerate([s for s, kk in zip(spec, keep) if kk]):
        f = np.degrees(1.0) if is_angular(key, i) else 1.0
        unit = "deg/(N·m)" if key == "compliance" else "deg" if f != 1.0 else "mm"
        estimates[name] = {"delta": float(sol.x[k] * f), "se": float(se[k] * f), "unit": unit}
    # compliance as the stiffness a robot datasheet quotes (N·m/rad): 1 / (c0 + delta)
    c = geometry["compliance"].numpy()
    stiffness = {f"k{j + 1}": float(1.0 / c[j]) for j in range(6) if f"c{j + 1}" in estimates and c[j] > 0}
    with torch.no_grad():
        (p_before, R_before), (p_after, R_after) = (
            predicted(q, v, g0, S, station, tools0, R_meas is not None) for v in (x0, x))
    before, after = errors_3d(p_before.numpy(), p_meas), errors_3d(p_after.numpy(), p_meas)
    if R_meas is not None:
        before["orientation"] = orientation_errors(R_before.numpy(), np.asarray(R_meas, float))
        after["orientation"] = orientation_errors(R_after.numpy(), np.asarray(R_meas, float))
    report = {
        "n_points": len(p_meas),
        "identified": [n for n, k in zip(names, keep) if k],
        "fixed": ident["fixed"],
        "estimates": estimates,
        "stations": {st: (S["station"] @ x).reshape(-1, 6)[k].tolist() for k, st in enumerate(stations)},
        "stations_units": "[rx, ry, rz] rad, [tx, ty, tz] mm: p_station = R p_first + t (first: zeros)",
        "station_tools": {st: v.tolist() for st, v in zip(stations, station_tools(x, S, tools0))},
        "station_tools_units": "mm in the flange frame: the station's tool minus the first station's",
        "fixed_because_of_stations": fixed_by_stations,
        "stiffness_Nm_per_rad": stiffness,
        "condition_number": ident["condition"],
        "rank": ident["rank"], "n_candidates": P,
        "residual_sigma_mm": float(np.sqrt(sigma2)),
        "before": before, "after": after,
        "loss": cfg["loss"], "loss_scale_mm": cfg["loss_scale_mm"],
        "nfev": int(sol.nfev), "njev": int(sol.njev or 0), "status": sol.message,
        "seconds": time.perf_counter() - t0,
    }
    if R_meas is not None:
        report["orientation_weight_mm_per_rad"] = weight
    return geometry, report
