"""A TCP path's geometry (docs/robot-cell.md, "Compensating a path"): straight lines and circular arcs
between waypoints, resampled along the arc length, and the distance of any point to the path.

    read_path(path, robot)           the file's waypoints: positions (or joints: their nominal positions),
                                     moves, the start joints; bad input is an IngestError naming file, row
                                     (the header is row 1) and column
    segments(points, moves, where)   Line and Arc segments; a bad move is a ValueError naming where(i)
    resample(segs, spacing_mm)       samples at most spacing_mm apart along the path, every waypoint one
    at(segs, arc_mm)                 the path's points at arc lengths
    rotations_at(segs, rots, arc_mm) its orientations there, slerped from waypoint to waypoint
    distance(points, segs)           each point's distance to the path (mm)

Moves, as a UR program's: `movel` and `movep` a straight line from the previous point; `via` then
`movec` a circular arc from the previous point through the via point to the movec's (URScript
movec(pose_via, pose_to)). A movej has no TCP path to follow, so it is refused. An orientation turns
from a segment's first waypoint's to its last's in proportion to the arc length (a movec's via point's
orientation is not used, as in URScript's movec).
"""
import math
import re
import unicodedata
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.lib.project.columns import JOINTS_DEG, TARGET
from pipeline.lib.project.config import logger
from pipeline.lib.reading.readers import (IngestError, find_column, headers_found, looks_like_radians,
                                          parse_number, read_table, shape_problems, unit_of)

MOVES = ("movel", "movep", "via", "movec")
ROTVEC = ["target_rx", "target_ry", "target_rz"]           # a TCP orientation: UR's rotation vector, rad
ROTVEC_MAX_RAD = np.pi + 1e-9                              # a rotation vector no longer than π (UR's)
JOINT_NAMES = ([f"j{i}_deg" for i in range(1, 7)], [f"j{i}_rad" for i in range(1, 7)],
               [f"actual_q_{i}" for i in range(6)])
READ_NAMES = {*TARGET, *ROTVEC, *(n for names in JOINT_NAMES for n in names), "point_id", "move"}   # what is read
MIN_MOVE_MM = 1e-6                                         # a move shorter than this goes nowhere


MISNAMED = re.compile(r"""(                           # an unused column named like a target's: refused
    (target|tgt|tcp|pos|position)[ _.-]?r?[xyz]([ _.(\[-]|$)     # target_x_mm, target.x, pos_x (not target_q_0)
  | t[xyz]$                                                    # tx
  | r?[xyz]([ _.(\[-]*(mm|m|rad|deg)[)\]]?)?$                   # x, x_mm, X (mm), z [mm], rx
)""", re.I | re.X)
log = logger(__name__)


@dataclass
class Line:
    start: np.ndarray
    end: np.ndarray
    waypoints: tuple = (0, 1)       # the waypoints (indices) it runs from and to

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    def at(self, s: np.ndarray) -> np.ndarray:
        """Points at arc lengths s (k,) from the start -> (k, 3)."""
        return self.start + (s / self.length)[:, None] * (self.end - self.start)

    def distance(self, p: np.ndarray, lo=0.0, hi=None) -> np.ndarray:
        """Each point's (k, 3) distance to the line between arc lengths lo and hi (scalars or (k,))."""
        d = self.end - self.start
        hi = self.length if hi is None else hi
        u = np.clip((p - self.start) @ d / (d @ d), lo / self.length, hi / self.length)
        return np.linalg.norm(p - self.start - u[:, None] * d, axis=1)


@dataclass
class Arc:
    """The circle through start, via and end, from start through via to end."""
    start: np.ndarray
    via: np.ndarray
    end: np.ndarray
    waypoints: tuple = (0, 2)       # the waypoints (indices) it runs from and to (the via between)

    def __post_init__(self):
        a, b, c = self.start, self.via, self.end
        if np.linalg.norm(c - a) < 1e-9:
            raise ValueError("the arc ends where it starts: a whole circle has no one plane through its three points "
                             "(as URScript's movec: two movec, each through a via point)")
        n = np.cross(b - a, c - b)
        if np.linalg.norm(n) < 1e-9 * max(1.0, np.linalg.norm(b - a) * np.linalg.norm(c - b)):
            raise ValueError("the via point lies on the line through the arc's ends: no circle")
        self.normal = n / np.linalg.norm(n)
        ab, ac = b - a, c - a                                # the circumcentre, in the plane of a, b, c
        w = np.cross(ab, ac)
        self.centre = a + (np.cross(w, ab) * (ac @ ac) + np.cross(ac, w) * (ab @ ab)) / (2 * (w @ w))
        self.radius = float(np.linalg.norm(a - self.centre))
        self.e1 = (a - self.centre) / self.radius
        self.e2 = np.cross(self.normal, self.e1)            # a -> b -> c turns about the normal
        self.sweep = float(self._angle(c[None])[0])

    def _angle(self, p: np.ndarray) -> np.ndarray:
        v = p - self.centre
        return np.arctan2(v @ self.e2, v @ self.e1) % (2 * np.pi)

    @property
    def length(self) -> float:
        return self.radius * self.sweep

    def at(self, s: np.ndarray) -> np.ndarray:
        t = s / self.radius
        return self.centre + self.radius * (np.cos(t)[:, None] * self.e1 + np.sin(t)[:, None] * self.e2)

    def distance(self, p: np.ndarray, lo=0.0, hi=None) -> np.ndarray:
        """Each point's (k, 3) distance to the arc between arc lengths lo and hi (scalars or (k,)): within
        that sweep, to its circle; beyond, to the nearer end."""
        v = p - self.centre
        h = v @ self.normal
        r = np.linalg.norm(v - h[:, None] * self.normal, axis=1)
        on = np.hypot(h, r - self.radius)
        if hi is None and np.all(lo == 0.0):
            a, b, hi = self.start, self.end, self.length
        else:
            a, b = (self.at(np.broadcast_to(x, len(p)).astype(float)) for x in (lo, hi))
        ends = np.minimum(np.linalg.norm(p - a, axis=-1), np.linalg.norm(p - b, axis=-1))
        t = self._angle(p)
        return np.where((t >= lo / self.radius) & (t <= hi / self.radius), on, ends)


def segments(points: np.ndarray, moves: list, where=lambda i: f"point {i}") -> list:
    """The path's segments from its points (n, 3) and moves (n; the first is the start, "" or "start");
    a ValueError naming where(i) for a bad or degenerate move."""
    moves = [str(m).strip().lower() for m in moves]
    if len(points) < 2:
        raise ValueError(f"{where(0)}: a path needs at least two points")
    if moves[0] not in ("", "start"):
        raise ValueError(f"{where(0)}: the first point is the path's start ('start' or empty), not {moves[0][:20]!r}")
    out, i = [], 1
    while i < len(points):
        m = moves[i]
        if m not in MOVES:
            hint = ": a movej has no TCP path; split the program there" if m == "movej" else ""
            raise ValueError(f"{where(i)}: move {m[:20]!r} is not one of {', '.join(MOVES)}{hint}")
        if m == "movec" or (m == "via" and (i + 1 == len(points) or moves[i + 1] != "movec")):
            raise ValueError(f"{where(i)}: a movec needs one via point just before it (move 'via', then 'movec')")
        if m == "via":
            ends = [points[i - 1], points[i], points[i + 1]]
            if min(np.linalg.norm(ends[1] - ends[0]), np.linalg.norm(ends[2] - ends[1])) < MIN_MOVE_MM:
                raise ValueError(f"{where(i)}: the via point is one of the arc's ends")
            try:
                out.append(Arc(*ends, waypoints=(i - 1, i + 1)))
            except ValueError as e:
                raise ValueError(f"{where(i)}: {e}") from None
            i += 2
            continue
        if np.linalg.norm(points[i] - points[i - 1]) < MIN_MOVE_MM:
            raise ValueError(f"{where(i)}: the same point as the one before: a move of length 0")
        out.append(Line(points[i - 1], points[i], waypoints=(i - 1, i)))
        i += 1
    return out


def counts(segs: list, spacing_mm: float) -> np.ndarray:
    """Steps per segment: each segment cut in equal steps of at most spacing_mm."""
    return np.array([max(1, int(np.ceil(s.length / spacing_mm - 1e-9))) for s in segs])


def n_samples(segs: list, spacing_mm: float) -> int | float:
    """How many samples `resample` makes at spacing_mm (to check before making them): beyond 1e15, as a float
    (said as 1e+302, not in 303 digits); inf where a float cannot count them (a spacing of 1e-320 mm)."""
    with np.errstate(over="ignore"):
        steps = np.array([s.length for s in segs]) / spacing_mm
    if not np.isfinite(steps).all():
        return math.inf
    n = int(np.maximum(1, np.ceil(steps - 1e-9)).sum()) + 1
    return n if n < 10 ** 15 else float(f"{n:.3g}")


def resample(segs: list, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(points (m, 3), arc_mm (m,)): the path's start, then each segment's equal steps of at most
    spacing_mm; every segment's end is a sample."""
    pts, arc, s0 = [segs[0].at(np.zeros(1))], [np.zeros(1)], 0.0
    for seg, k in zip(segs, counts(segs, spacing_mm)):
        s = seg.length * np.arange(1, k + 1) / k
        pts.append(seg.at(s))
        arc.append(s0 + s)
        s0 += seg.length
    return np.concatenate(pts), np.concatenate(arc)


def locate(segs: list, arc_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc lengths along the path (k,) -> each one's segment (k,) and arc length within it (k,) mm."""
    ends = np.cumsum([s.length for s in segs])
    k = np.minimum(np.searchsorted(ends, arc_mm), len(segs) - 1)
    lengths = np.array([s.length for s in segs])[k]
    return k, np.clip(arc_mm - (ends[k] - lengths), 0.0, lengths)


def at(segs: list, arc_mm: np.ndarray) -> np.ndarray:
    """The path's points at arc lengths arc_mm (k,) -> (k, 3)."""
    k, s = locate(segs, arc_mm)
    out = np.empty((len(arc_mm), 3))
    for i in np.unique(k):
        sel = k == i
        out[sel] = segs[i].at(s[sel])
    return out


def rotations_at(segs: list, rots: np.ndarray, arc_mm: np.ndarray) -> np.ndarray:
    """The path's orientations (k, 3, 3) at arc lengths arc_mm (k,), from the waypoints' rots (n, 3, 3): along
    each segment, the rotation from its first waypoint's to its last's, slerped by the share of its length."""
    k, s = locate(segs, arc_mm)
    out = np.empty((len(arc_mm), 3, 3))
    for i in np.unique(k):
        sel, (a, b) = k == i, segs[i].waypoints
        r0 = Rotation.from_matrix(rots[a])
        turn = (r0.inv() * Rotation.from_matrix(rots[b])).as_rotvec()          # (3,) rad, in the first's frame
        out[sel] = (r0 * Rotation.from_rotvec((s[sel] / segs[i].length)[:, None] * turn)).as_matrix()
    return out


def distance(points: np.ndarray, segs: list) -> np.ndarray:
    """Each point's (n, 3) distance to the path (mm): the nearest of its segments."""
    return np.min([s.distance(np.asarray(points, float)) for s in segs], axis=0)


def step_distance(points: np.ndarray, segs: list, arc_mm: np.ndarray) -> np.ndarray:
    """Each step's point (m - 1, 3) distance (mm) to the part of the path the step spans, arc_mm[k] to
    arc_mm[k + 1] (m,): not to the whole path, which a path coming back near itself (out and back, a closed
    contour) would find beside a step that cuts across."""
    points, arc = np.asarray(points, float), np.asarray(arc_mm, float)
    a, b = np.minimum(arc[:-1], arc[1:]), np.maximum(arc[:-1], arc[1:])
    ends = np.concatenate([[0.0], np.cumsum([s.length for s in segs])])
    out = np.full(len(points), np.inf)
    for i, s in enumerate(segs):
        sel = (a <= ends[i + 1]) & (b >= ends[i])
        if sel.any():
            lo, hi = (np.clip(x[sel] - ends[i], 0.0, s.length) for x in (a, b))
            out[sel] = np.minimum(out[sel], s.distance(points[sel], lo, hi))
    return out


@dataclass
class PathFile:
    """A path file's waypoints."""
    points: np.ndarray             # (n, 3) mm, base frame
    moves: list                    # (n,) the move reaching each point ("" for the start)
    joints_deg: np.ndarray | None  # (n, 6) the file's joints, where it gives them
    rotvec: np.ndarray | None      # (n, 3) rad, where it gives an orientation
    lines: list                    # each waypoint's row in the file (the header is row 1)
    path: str
    segs: list | None = None       # its segments (`segments`)
    offline: bool = False          # its points are where the nominal kinematics put its joints
    columns: str = "move"          # what a bad move names: the move column, or the positions without one

    def where(self, i: int) -> str:
        return f"{self.path}, row {self.lines[i]}, column {self.columns}"


def check_rotvecs(rotvec: np.ndarray, path, lines: list) -> None:
    """An IngestError naming the first row of rotvec (n, 3) rad longer than π (UR's rotation vectors are at
    most π long; a longer one is degrees, or not an angle: 1e300 rad turns into NaN)."""
    with np.errstate(over="ignore"):                       # 1e300: inf long, refused below
        norms = np.linalg.norm(rotvec, axis=1)
    bad = np.flatnonzero(~(norms <= ROTVEC_MAX_RAD))
    if len(bad):
        r = int(bad[0])
        raise IngestError(f"a rotation vector {norms[r]:.4g} rad long, more than π: target_rx..target_rz in "
                          "radians (degrees given?)", file=path, row=lines[r], column=ROTVEC[0])


def check_unused(header: list, used: set, path, known: str, also=None) -> None:
    """An IngestError naming a column the reader did not use whose name looks like a target's (a typo,
    `target_x_mm`, would leave the targets unread: waypoints solved as offline ones, a path driven through
    the joints' nominal positions, without a word) or matches the pattern `also` (the reader's own, e.g. a
    path's `move_type`), read as Unicode reads it (NFKC, invisible characters left out: `target_x` with a
    zero-width space, a full-width `ｘ`), or is so read a column the readers read; the other unused
    columns are logged. known: the reader's columns, for the message."""
    unused = [h for c, h in enumerate(header) if c not in used and h.strip()]
    for h in unused:
        plain = "".join(ch for ch in unicodedata.normalize("NFKC", h) if unicodedata.category(ch) != "Cf").strip()
        odd = " (it holds a character read as another or as none: retype it)" if plain != h.strip() else ""
        if (MISNAMED.match(plain) or (also is not None and also.search(plain))
                or (odd and plain.lower() in READ_NAMES)):      # target_x with a zero-width space: not target_x
            raise IngestError(f"a column this reader does not know{odd}: its columns are {known}: rename or "
                              "remove it", file=path, column=h)
    if unused:
        log.warning("%s: column(s) not used: %s", path, ", ".join(unused)[:200])


def read_path(path, robot, nominal_fk=None) -> PathFile:
    """The path file: target_x..z (base frame, mm) and/or the joints (j1_deg..j6_deg, j1_rad..., actual_q_0...:
    without targets, a waypoint is where nominal_fk(joints) puts it), optional move and target_rx..rz. Every
    bad cell is an IngestError naming file, row and column."""
    path = str(path)
    header, cells, lines, _, decimal = read_table(path, "auto", "auto")
    lower = [h.lower() for h in header]
    for r, problem in enumerate(shape_problems(cells, header)):
        if problem:
            raise IngestError(problem, file=path, row=lines[r])
    groups = {}
    for name, options in (("target", [TARGET]), ("rotvec", [ROTVEC]), ("joints", JOINT_NAMES)):
        for names in options:
            have = [n for n in names if n in lower]
            if 0 < len(have) < len(names):
                raise IngestError(f"columns {', '.join(names)} go together; found only {', '.join(have)}",
                                  file=path, column=next(n for n in names if n not in lower))
            if have:
                groups[name] = names
                break
    if "target" not in groups and "joints" not in groups:
        raise IngestError(f"a path needs target_x, target_y, target_z or the joints j1_deg..j6_deg; "
                          f"{headers_found(header)}", file=path)
    check_unused(header, {lower.index(n) for names in groups.values() for n in names}
                 | {c for c, h in enumerate(lower) if h == "move"}, path,
                 f"{', '.join(TARGET)}, {JOINTS_DEG[0]}..{JOINTS_DEG[-1]} (or *_rad, actual_q_*), move and "
                 f"{', '.join(ROTVEC)}", also=re.compile("move", re.I))

    def numbers(names):
        cols = [find_column(header, n, "path", path) for n in names]
        out = np.empty((len(cells), len(cols)))
        for r, row in enumerate(cells):
            for k, c in enumerate(cols):
                out[r, k], err = parse_number(row[c], decimal)
                if err or not np.isfinite(out[r, k]):
                    raise IngestError(f"not a finite number ({err[1] if err else row[c].strip()})", file=path,
                                      row=lines[r], column=header[c])
        return out

    joints = None
    if "joints" in groups:
        joints = numbers(groups["joints"])
        if unit_of(groups["joints"][0], "deg") == "rad":
            joints = np.degrees(joints)
        elif looks_like_radians(joints):
            raise IngestError("every joint angle lies within ±6.29: these look like radians in *_deg columns",
                              file=path)
        beyond = robot.check_joints(joints)
        if beyond.any():
            r, j = map(int, np.argwhere(beyond)[0])
            raise IngestError(f"{joints[r, j]:g}° beyond the joint limits {robot.limits_deg[j].tolist()}°",
                              file=path, row=lines[r], column=header[find_column(header, groups['joints'][j],
                                                                                   'path', path)])
    points = numbers(TARGET) if "target" in groups else nominal_fk(joints)
    rotvec = numbers(ROTVEC) if "rotvec" in groups else None
    if rotvec is not None:
        check_rotvecs(rotvec, path, lines)
    moves = [""] + ["movel"] * (len(cells) - 1)
    columns = ", ".join(header[find_column(header, n, "path", path)] for n in groups.get("target", groups.get("joints")))
    if "move" in lower:
        c = find_column(header, "move", "path", path)
        moves, columns = [row[c] for row in cells], repr(header[c])
    found = PathFile(points, moves, joints, rotvec, lines, path, offline="target" not in groups, columns=columns)
    try:
        found.segs = segments(points, moves, found.where)
    except ValueError as e:
        raise IngestError(str(e)) from None
    return found
