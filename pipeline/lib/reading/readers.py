"""Reading tracker/controller exports -> one table of points (docs/data-format.md).

`ingest(cfg, robot)` does it all and writes nothing (the ingest stage writes).
Inputs, chosen by settings alone (the `ingest:` section, and the robot of `robot:`):
- paired files: `ingest.joints` (point_id, j1_deg..j6_deg) and `ingest.tracker`
  (Name, X, Y, Z), paired by point id; or a tracker point cloud
  (.ply/.pcd/.xyz/.pts, read with open3d), paired with the joint rows by order
  (counts must match; ids come from the joints file);
- one table with joints and positions together: `ingest.joints` and
  `ingest.tracker` name the same file; ids from
  `columns.point_id`, else a point_id/name/id column, else the row number
  ("R0001" = first data row).
Headers match ignoring case and surrounding spaces. `columns.point_id` is one
header (both files) or [joints header, tracker header]. Separator (`,` `;` tab)
is sniffed from the header line and the decimal mark (`.` `,`) from the cells,
unless set. A joint column's name fixes its unit (`*_rad`, `actual_q_*`:
radians; `*_deg`: degrees), otherwise `angle_unit` does; positions are in
`length_unit`.
The probe's orientation (optional, never guessed), read from the tracker file (the
table in one-table mode) by lib/reading/orientation.py:
- `columns.orientation`: 3 (Euler), 4 (quaternion) or 9 (matrix) headers, read as
  `ingest.orientation` says (kind, sequence, angle_unit, scalar_first);
- `columns.marker`: a rigid multi-marker target, one tracker row per marker, several per
  id (paired files only): each pose is the target frame fitted by Kabsch to
  `ingest.target` (its markers in its own frame), or to the geometry estimated from
  the poses (null: origin at the markers' centroid); a marker farther than
  `target_residual_mm` from its pose's fit is removed and the pose refitted.

Output, data/interim/ingest.parquet, rows in input order (of the joints file):
    point_id (str), j1_deg..j6_deg (degrees), meas_x, meas_y, meas_z (mm, the file's frame),
    with an orientation meas_qw, meas_qx, meas_qy, meas_qz (unit quaternion, w >= 0, of the
    rotation probe -> tracker; no such columns without one),
    then every other input column under its own header (float if every kept cell
    is a number, else text); a name already taken gets its file's role as a
    prefix ("tracker_x"), a blank header becomes "<role>_col<k>" (none where its cells are empty too:
    a trailing separator).
and reports/ingest.json: files, n_read (data rows per file), n_kept, dropped
[{point_id, file, row, reason, detail}], dropped_counts {reason: n}, units (with
an orientation: units.orientation), geometry, gross_outlier (and target, for a
multi-marker target). `row` is the 1-based line number in the file, header
included (for a point cloud: the 1-based point index; a target's pose: each of
its marker rows).

A per-row problem drops the row and lists it; `reason` is one of
    field_count      more or fewer cells than the header (a stray separator?); empty cells
                     after the last column pass when most rows have them (trailing separator)
    missing_id       the id cell (or a target's marker cell) is empty
    duplicate        id already used by an earlier row of the same file (the first row
                     keeps the id, even if that row is itself dropped for another reason);
                     a target's file: the same id and marker
    empty, nan, non_numeric   a joint/position/orientation cell (the detail names the column)
    non_finite       a joint/position/orientation cell reads as +-inf ('inf', or 1e999: a mistyped exponent?)
    bad_rotation     orientation cells that are no rotation: a quaternion whose norm is off 1 by
                     more than 1e-3, a matrix not orthonormal within 1e-3 or a reflection, an Euler
                     angle beyond one turn
    marker_residual  a target's marker farther than target_residual_mm from its pose's fit
    too_few_markers  a target's pose with fewer than 3 usable markers, or markers (nearly) on a
                     line (its marker rows)
    unpaired         id in one file only
    partner_dropped  the point's row in the other file was dropped
    joint_limit      an angle outside the robot's limits (also a joint cell that lost its decimal point)
    position_outlier a position farther than POSITION_FAR = 5 x (robot reach + |tool|) from the
                     median position (per axis, of the points left), where no real point can be: a
                     cell that lost its decimal point; the detail names the column(s) off. Judged
                     before the scale check, which then judges the rest; when more than half the
                     points are that far (a wrong length_unit), none is dropped: the scale check
                     judges them all and stops, as it did before this rule
    gross_outlier    for point i, median_j | |m_i-m_j| - |t_i-t_j| | > gross_outlier_mm,
                     t = nominal FK with tool (frame-free: rigid-motion invariant); j runs over
                     every other point up to REFERENCE_POINTS = 4096 points, beyond that over
                     4096 reference points drawn with a fixed seed (the same for the same count;
                     gross_outlier.reference_points in the summary), so the check stays linear
A dropped point lists its row in every file it has one in, so for each file
n_kept + (dropped rows of that file) == n_read (a target's tracker file: the
kept poses' marker rows + its dropped rows == n_read).

Fatal problems raise IngestError, whose message names file, row and column:
    unreadable file, no header (only separators and empty cells), no data rows, a missing
    or ambiguous required column
    (the headers found are listed), an unbalanced quote;
    more than half of a file's rows with bad cells (wrong sep/decimal setting?)
    or out of joint limits (degrees read as radians?);
    point cloud and joint rows of different counts; no ids in common;
    a position scale that does not fit the robot (extent of the points left
    outside reach/50 .. 50*reach after length_unit) or degree angles all
    within +-2*pi (radians?);
    the gross-outlier check flagging more than half the points (wrong robot,
    tool or units); fewer than 10 points left; measured points (nearly)
    collinear or coincident. Nearly coplanar points only warn (geometry.coplanar).
    Orientation: more than half the rows no rotation (bad_rotation); Euler angles that look like
    the other unit (orientation.unit_mismatch); orientation
    settings that do not fit together (kind and header count; orientation and
    marker both; a target without a marker column; a marker column in one table);
    orientation or markers asked of a point cloud; a target's marker not in
    ingest.target, its markers on a line, or (estimated) no pose with every marker.
"""
import codecs
import csv
import io
import math
import re
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.lib.project.columns import CAMPAIGN, JOINTS_DEG, MEAS, MEAS_Q, STATION
from pipeline.lib.project.config import check_keys, check_values, logger
from pipeline.lib.reading import orientation
from pipeline.lib.robot.kinematics import fk_numpy

log = logger(__name__)

CLOUD_SUFFIXES = {".ply", ".pcd", ".xyz", ".pts"}
MIN_POINTS = 10
SCALE_RANGE = 50.0          # positions must span reach/50 .. 50*reach (mm)
FLAT_RATIO = 1e-2           # singular value ratio below which the points are a line / plane
AUTO_ID = {"joints": ["point_id", "name", "id"], "tracker": ["name", "point_id", "id"],
           "table": ["point_id", "name", "id"]}
AUTO_JOINTS = [JOINTS_DEG, [f"j{i}_rad" for i in range(1, 7)],
               [f"actual_q_{i}" for i in range(6)], [f"j{i}" for i in range(1, 7)]]
AUTO_POSITION = [["x", "y", "z"], MEAS]
CELL_REASONS = ("field_count", "missing_id", "empty", "nan", "non_numeric")
NAN_WORDS = {"nan", "-nan", "na", "n/a", "null", "none"}
INF_WORDS = {"inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}
POSITION_FAR = 5.0          # x (reach + |tool|): real points lie within (1 + sqrt 3) x that of their
                            # per-axis median; a lost decimal point puts a cell 10..10^4 x off
NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?", re.ASCII)
NUMBERS = re.compile(r"(?:[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\n)*", re.ASCII)    # NUMBER, one per line
COMMA_DECIMAL = re.compile(r"[+-]?\d*,\d+([eE][+-]?\d+)?", re.ASCII)
THOUSANDS = re.compile(r"[+-]?\d{1,3}(,\d{3})+", re.ASCII)   # "1,234": a grouping, not a decimal comma, in a ',' file
POINT_START = re.compile(r"[+-]?(\d|\.\d|nan|inf)", re.I | re.ASCII)  # a text cloud's line that begins as a point does
DOT_DECIMAL = re.compile(r"[+-]?\d*\.\d+([eE][+-]?\d+)?", re.ASCII)
REFERENCE_POINTS = 4096       # the gross-outlier check scores a point against at most this many others
REFERENCE_SEED = 0            # which, when there are more points (reference_points)
PROGRESS_POINTS = 50_000      # a log line per this many points scored (more than REFERENCE_POINTS only)
SEPARATORS = {",": ",", ";": ";", "\t": "\t", "tab": "\t", "\\t": "\t"}


class IngestError(ValueError):
    """Bad input that stops the stage; `file`, `row`, `column` say where."""

    def __init__(self, message: str, file=None, row=None, column=None):
        self.message, self.file, self.row, self.column = message, file, row, column
        where = [str(file)] if file is not None else []
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column '{column}'")
        super().__init__(", ".join(where) + ": " + message if where else message)


# -------------------------------------------------------------------- reading

@dataclass
class Rows:
    """One input file's data rows: ids, the required numbers, and each row's problem."""
    path: str
    role: str                       # joints | tracker | table
    lines: list                     # 1-based line number (or point index) of each row
    ids: list                       # point id of each row ("" if none)
    values: np.ndarray              # (n, k) the required columns, NaN where unreadable
    problem: list                   # None or (reason, detail, column) per row
    headers: list = field(default_factory=list)   # the k required columns' headers
    extras: list = field(default_factory=list)    # [(header, [cell per row])]
    sep: str | None = None
    decimal: str = "."
    groups: dict = field(default_factory=dict)    # what (joints, position, orientation, marker) -> its headers
    quat: np.ndarray | None = None                # (n, 4) the orientation columns as unit quaternions (w first)
    markers: list | None = None                   # each row's marker name (a multi-marker target's file)
    members: list | None = None                   # one row per pose (a target): the file lines it stands for
    n_lines: int | None = None                    # ... and the file's data rows
    failed: dict = field(default_factory=dict)    # a target's pose whose every row failed its own checks: its lines

    @property
    def n_read(self) -> int:
        """The file's data rows."""
        return len(self.lines) if self.n_lines is None else self.n_lines

    def lines_of(self, r: int) -> list:
        """The file lines row r stands for: its own, or a pose's marker rows."""
        return [self.lines[r]] if self.members is None else self.members[r]

    def first_rows(self) -> dict:
        """id -> index of the first row with that id (whatever its problems)."""
        out = {}
        for r, pid in enumerate(self.ids):
            if pid:
                out.setdefault(pid, r)
        return out


def read_text(path: str) -> str:
    """File contents as text (UTF-16 with its BOM, as spreadsheet programs export "Unicode text"; UTF-8,
    with or without BOM; else Latin-1)."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise IngestError(f"cannot read the file ({e.strerror})", file=path) from None
    if data[:2] in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        try:
            return data.decode("utf-16")
        except UnicodeDecodeError as e:
            raise IngestError(f"starts as UTF-16 but byte {e.start} is not ({e.reason})", file=path) from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:                    # its mark (a UTF-8 file with one byte that is not) not text
        return data.removeprefix(codecs.BOM_UTF8).decode("latin-1")


def sniff_sep(header_line: str) -> str:
    """The separator used most in the header line (',' if none)."""
    counts = {s: header_line.count(s) for s in ("\t", ";", ",")}
    best = max(counts, key=counts.get)
    return best if counts[best] else ","


def sniff_decimal(cells: list, sep: str) -> str:
    """',' when the cells hold more decimal-comma numbers than decimal-point ones (with sep ',', only
    quoted cells can hold a decimal comma)."""
    flat = [c.strip() for row in cells for c in row]
    if sep == ",":                                          # only quoted cells can hold one; "1,234" is grouping
        flat = [c for c in flat if not THOUSANDS.fullmatch(c)]
    commas = sum(bool(COMMA_DECIMAL.fullmatch(c)) for c in flat)
    dots = sum(bool(DOT_DECIMAL.fullmatch(c)) for c in flat)
    return "," if commas > dots else "."


def split_records(text: str, sep: str, path: str):
    """CSV records with the line number of each; blank lines skipped."""
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=sep, skipinitialspace=True)   # `"a", "b"`: a, b
    records, last = [], 0
    try:
        for rec in reader:
            line = reader.line_num
            if line - last > 1:
                closed = rec and not rec[-1].endswith("\n") and line < text.count("\n") + 1
                raise IngestError((f"a quoted cell holds a line break (the record runs over lines {last + 1}.."
                                   f"{line}): one record per line" if closed else
                                   f"a quote opened on this line is never closed (the cell runs to line {line})"),
                                  file=path, row=last + 1)
            last = line
            if "".join(rec).strip():                       # not a blank record (every cell whitespace)
                records.append((line, rec))
    except csv.Error as e:
        raise IngestError(f"not a readable table ({e})", file=path, row=reader.line_num) from None
    return records


def skipped(skip_lines: int) -> str:
    """What an error adds where ingest.skip_lines may have cut a file's header ("" where it is 0)."""
    return (f"; ingest.skip_lines = {skip_lines} leaves out the first {skip_lines} line(s) of every input "
            f"file, so this one's header was looked for from line {skip_lines + 1} on" if skip_lines else "")


def read_table(path: str, sep: str, decimal: str, skip_lines: int = 0):
    """A delimited text table, its first `skip_lines` lines (a preamble) left out -> (header, cells per row,
    line numbers in the file, sep, decimal)."""
    text = whole = read_text(path)
    if skip_lines:                                   # blanked, not cut: line numbers stay the file's
        lines = re.split(r"\r\n|\r|\n", text)           # any line end (CR alone: a Mac export), as csv reads them
        text = "\n" * min(skip_lines, len(lines)) + "\n".join(lines[skip_lines:])
    header_line = next((ln for ln in text.splitlines() if ln.strip()), None)
    if header_line is None:
        raise IngestError("the file is empty" if not whole.strip() else
                          f"nothing to read{skipped(skip_lines)}", file=path)
    sep = sniff_sep(header_line) if sep == "auto" else sep
    records = split_records(text, sep, path)
    if not records:
        raise IngestError(f"no header: every line is blank or holds only separators ({sep!r}) and empty cells",
                          file=path)
    header = [h.strip() for h in records[0][1]]
    body = records[1:]
    if not body:
        raise IngestError(f"no data rows below the header ({', '.join(header)}){skipped(skip_lines)}", file=path)
    cells = [rec for _, rec in body]
    decimal = sniff_decimal(cells, sep) if decimal == "auto" else decimal
    return header, cells, [line for line, _ in body], sep, decimal


def parse_number(cell: str, decimal: str):
    """(value, None) or (nan, (reason, message)) for one cell."""
    s = cell.strip()
    t = s.replace(",", ".") if decimal == "," else s
    if NUMBER.fullmatch(t) and not (decimal == "," and "." in s):
        return float(t), None
    if not s:
        return np.nan, ("empty", "empty cell")
    if s.lower() in NAN_WORDS:
        return np.nan, ("nan", f"{s!r} (missing value)")
    if s.lower() in INF_WORDS:
        return float(s), None
    return np.nan, ("non_numeric", f"{s!r} is not a number")


def parse_column(cells: list, decimal: str) -> np.ndarray | None:
    """parse_number's values of a whole column of cells at once (one regex scan, no call per cell), or None
    when any cell is not a plain finite number: then parse_number, cell by cell, says which and why."""
    text = "\n".join(c.strip() for c in cells) + "\n"
    if decimal == ",":
        if "." in text:
            return None
        text = text.replace(",", ".")
    parts = text.split("\n")[:-1]
    if len(parts) != len(cells) or not NUMBERS.fullmatch(text):      # a cell holding a line break: cell by cell
        return None
    v = np.fromiter(map(float, parts), float, len(parts))
    return v if np.isfinite(v).all() else None


def parse_finite(cell: str, decimal: str):
    """parse_number, and a non-finite value (inf, 1e999) is the `non_finite` problem."""
    v, err = parse_number(cell, decimal)
    if err is None and not math.isfinite(v):
        return np.nan, ("non_finite", f"{cell.strip()!r} reads as {v} (a mistyped number?)")
    return v, err


def headers_found(header: list) -> str:
    preamble = len(header) >= 1 and header[0].lstrip().lower().startswith(("//", "#", "sep="))   # sep=: Excel's
    hint = (" (a comment or preamble line above the header? set ingest.skip_lines)" if preamble else
            " (a single column: is ingest.sep right?)" if len(header) == 1 else "")
    return "headers found: " + ", ".join(repr(h) for h in header) + hint


def find_column(header: list, name: str, what: str, path: str) -> int:
    """Index of the header matching `name` (case and surrounding spaces ignored)."""
    key = str(name).strip().lower()
    hits = [i for i, h in enumerate(header) if h.lower() == key]
    if len(hits) == 1:
        return hits[0]
    if hits:
        raise IngestError(f"{what} column '{name}' appears {len(hits)} times in the header",
                          file=path, column=name)
    unset = " (a campaign without the probe's orientation: ingest.columns.orientation: null)" \
        if what == "orientation" else ""
    raise IngestError(f"missing {what} column '{name}'{unset}; {headers_found(header)}", file=path, column=name)


def pick_columns(header: list, setting, candidates: list, what: str, path: str) -> list:
    """Indices of a column group: the names in `setting`, else the first complete auto candidate."""
    if setting is not None:
        names = [str(n) for n in (setting if isinstance(setting, (list, tuple)) else [setting])]
        if len(names) != len(candidates[0]):
            raise IngestError(f"ingest.columns.{what} needs {len(candidates[0])} headers, "
                              f"got {names}", file="params.yaml")
        return [find_column(header, n, what, path) for n in names]
    have = {h.lower() for h in header}
    for names in candidates:
        if all(n.lower() in have for n in names):
            return [find_column(header, n, what, path) for n in names]
    best = max(candidates, key=lambda c: sum(n.lower() in have for n in c))
    missing = [n for n in best if n.lower() not in have]
    tried = " or ".join(f"{c[0]}..{c[-1]}" for c in candidates)
    raise IngestError(f"missing {what} column(s) {', '.join(missing)} (looked for {tried}; "
                      f"else set ingest.columns.{what}); {headers_found(header)}",
                      file=path, column=missing[0])


def pick_id(header: list, setting, role: str, path: str):
    """Index of the id column, or None (table without ids: row numbers)."""
    if setting is not None:
        return find_column(header, setting, "point id", path)
    for name in AUTO_ID[role]:
        if name in {h.lower() for h in header}:
            return find_column(header, name, "point id", path)
    if role == "table":
        return None
    raise IngestError(f"missing point id column (looked for {', '.join(AUTO_ID[role])}; else set "
                      f"ingest.columns.point_id); {headers_found(header)}",
                      file=path, column=AUTO_ID[role][0])


def row_ids(n: int) -> list:
    """Ids from row numbers: R0001, R0002, ... (wider when n needs it)."""
    width = max(4, len(str(n)))
    return [f"R{r + 1:0{width}d}" for r in range(n)]


def shape_problems(cells: list, header: list) -> list:
    """Per row: None, or why its cell count does not fit the header (the `field_count` rule of every table
    read here: ingest's files and a program's waypoints). Empty cells after the last column are a trailing
    separator when most rows have them (an export's style); on a few rows they mean a cell split in two by
    a stray separator or a decimal comma. Likewise a blank last header (a separator ending the header line
    alone) with most rows one cell short."""
    width = len(header)
    padded = [len(row) > width and not any(c.strip() for c in row[width:]) for row in cells]
    trailing_ok = 2 * sum(padded) > len(cells)
    short_ok = not header[-1] and 2 * sum(len(row) == width - 1 for row in cells) > len(cells)
    return [f"{len(row)} cells but the header has {width} (a separator or decimal comma inside a cell?)"
            if (len(row) < width and not (short_ok and len(row) == width - 1))
            or (len(row) > width and not (trailing_ok and pad)) else None
            for row, pad in zip(cells, padded)]


def cell(row: list, c: int) -> str:
    """Row's cell c, stripped ("" when the row is short)."""
    return row[c].strip() if c < len(row) else ""


def parse_row(row: list, keys: list, cols: list, header: list, decimal: str, out: np.ndarray):
    """None, or the row's problem: an empty key cell ([(column, "id" | "marker")]), else its first
    unreadable number; the numbers of `cols` go to `out`."""
    for c, what in keys:
        if not cell(row, c):
            return ("missing_id", f"empty {what} cell", header[c])
    for k, c in enumerate(cols):
        out[k], err = parse_finite(row[c], decimal)
        if err:
            return (err[0], f"column '{header[c]}': {err[1]}", header[c])
    return None


def read_rows(path: str, role: str, cfg: dict, id_setting, groups: list, marker=None) -> Rows:
    """Read a text table and check every row; groups = [(setting, candidates, what)] of required columns;
    marker: the header naming each row's marker (a multi-marker target), or None."""
    header, cells, lines, sep, decimal = read_table(path, cfg["sep"], cfg["decimal"], cfg["skip_lines"])
    try:
        id_col = pick_id(header, id_setting, role, path)
        picked = {what: pick_columns(header, setting, cands, what, path) for setting, cands, what in groups}
    except IngestError as e:                         # skip_lines cuts every file: was this one's header cut?
        if not cfg["skip_lines"]:
            raise
        raise IngestError(f"{e.message}{skipped(cfg['skip_lines'])}", file=e.file, row=e.row,
                          column=e.column) from None
    cols = [c for idx in picked.values() for c in idx]
    keys = [(id_col, "id")] if id_col is not None else []
    if marker is not None:
        keys.append((find_column(header, marker, "marker", path), "marker"))
    width, n = len(header), len(cells)
    ids = row_ids(n) if id_col is None else [cell(row, id_col) for row in cells]
    values = np.full((n, len(cols)), np.nan)
    shape = shape_problems(cells, header)
    problem = [("field_count", shape[r], None) if shape[r] else
               parse_row(row, keys, cols, header, decimal, values[r]) for r, row in enumerate(cells)]
    used = set(cols) | {c for c, _ in keys}
    unused = [(c, [row[c] if c < len(row) else "" for row in cells]) for c in range(width) if c not in used]
    extras = [(header[c] or f"{role}_col{c + 1}", v) for c, v in unused
              if header[c].strip() or any(x.strip() for x in v)]    # a trailing separator: no column
    rows = Rows(path, role, lines, ids, values, problem, [header[c] for c in cols], extras, sep, decimal,
                groups={what: [header[c] for c in idx] for what, idx in picked.items()})
    if marker is not None:
        rows.markers = [cell(row, keys[-1][0]) for row in cells]
        rows.groups["marker"] = [header[keys[-1][0]]]
    mark_duplicates(rows)
    check_mostly_readable(rows)
    return rows


def read_cloud(path: str) -> Rows:
    """A point cloud file (open3d) -> Rows with one row per point, in file order."""
    import open3d as o3d      # lazily: it needs system libraries the other stages don't
    if not Path(path).is_file():
        raise IngestError("no such file", file=path)
    if Path(path).suffix.lower() in (".xyz", ".pts"):
        check_text_cloud(path)
    pcd = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    pts = np.asarray(pcd.points, dtype=float)
    if len(pts) == 0:
        raise IngestError("no points read (empty, or not a point cloud open3d can read)", file=path)
    bad = ~np.isfinite(pts).all(axis=1)
    problem = [("nan", f"point {i + 1} has a non-finite coordinate", None) if b else None
               for i, b in enumerate(bad)]
    return Rows(path, "tracker", list(range(1, len(pts) + 1)), [""] * len(pts), pts, problem,
                ["x", "y", "z"], groups={"position": ["x", "y", "z"]})


def check_text_cloud(path: str) -> None:
    """An IngestError naming the first line of a text cloud (.xyz, .pts) that starts as a point does but is not
    three numbers apart by spaces (`1,2,3`; two numbers): open3d skips such a line without a word, and every
    point after it would pair with the wrong joint row. Lines that start otherwise (a header, `#` or `//`
    comments) are no points, to open3d too; a .pts file's first line may be its point count."""
    lines = read_text(path).splitlines()
    for k, line in enumerate(lines):
        cells = line.split()
        if not cells or not POINT_START.match(cells[0]) or (k == 0 and len(cells) == 1 and path.lower().endswith(".pts")):
            continue
        try:
            ok = len(cells) >= 3 and len([float(c) for c in cells[:3]]) == 3    # nan and inf: numbers, flagged later
        except ValueError:
            ok = False
        if not ok:
            raise IngestError(f"expected x y z, got {line.strip()[:40]!r}", file=path, row=k + 1)


def mark_duplicates(rows: Rows) -> None:
    """Every row after the first with the same id (a target's file: the same id and marker) gets the
    `duplicate` problem."""
    keys = rows.ids if rows.markers is None else list(zip(rows.ids, rows.markers))
    named = [bool(pid) and (rows.markers is None or bool(rows.markers[r])) for r, pid in enumerate(rows.ids)]
    first = {}
    for r, key in enumerate(keys):
        if named[r]:                                    # an empty marker cell is missing_id, no duplicate
            first.setdefault(key, r)
    for r, (pid, key) in enumerate(zip(rows.ids, keys)):
        field_count = rows.problem[r] and rows.problem[r][0] == "field_count"
        if named[r] and first[key] != r and not field_count:
            what = f"id {pid!r}" + (f" marker {rows.markers[r]!r}" if rows.markers is not None else "")
            rows.problem[r] = ("duplicate", f"{what} already on row {rows.lines[first[key]]}", None)


def check_mostly_readable(rows: Rows) -> None:
    """Stop if more than half the rows have unreadable cells: a setting is likely wrong."""
    bad = [r for r, p in enumerate(rows.problem) if p and p[0] in CELL_REASONS]
    if 2 * len(bad) > len(rows.problem):
        r = bad[0]
        reason, detail, column = rows.problem[r]
        detail = detail.split(": ", 1)[-1] if column else detail
        raise IngestError(f"{detail}; {len(bad)} of {len(rows.problem)} rows are unreadable "
                          f"like this: check ingest.sep / ingest.decimal (read with sep "
                          f"{rows.sep!r}, decimal {rows.decimal!r})",
                          file=rows.path, row=rows.lines[r], column=column)


# -------------------------------------------------------------------- orientation, multi-marker targets

def add_orientation(rows: Rows, spec: dict) -> None:
    """The orientation columns (the last of rows.values) as unit quaternions (rows.quat), read as `spec`
    (ingest.orientation); a row whose numbers are no rotation gets the `bad_rotation` problem."""
    headers = rows.groups.get("orientation")
    if not headers:
        return
    check_euler_unit(rows, spec, headers)
    rows.quat, why = orientation.rotations(rows.values[:, -len(headers):], spec)
    named = ", ".join(f"'{h}'" for h in headers)
    for r, w in enumerate(why):
        if w and rows.problem[r] is None:
            rows.problem[r] = ("bad_rotation", f"columns {named}: {w[0]}", headers[w[1]])
    bad = [r for r, p in enumerate(rows.problem) if p and p[0] == "bad_rotation"]
    if 2 * len(bad) > len(rows.problem):
        raise IngestError(f"{rows.problem[bad[0]][1]}; {len(bad)} of {len(rows.problem)} rows are no rotation "
                          f"like this: check ingest.orientation (kind {spec['kind']}) and ingest.columns.orientation",
                          file=rows.path, row=rows.lines[bad[0]], column=rows.problem[bad[0]][2])


def check_euler_unit(rows: Rows, spec: dict, headers: list) -> None:
    """Stop if Euler angles look like the other unit (orientation.unit_mismatch): like the joint angles."""
    if spec["kind"] != "euler":
        return
    v = rows.values[:, -len(headers):]
    finite = np.flatnonzero(np.isfinite(v).all(axis=1))
    found = orientation.unit_mismatch(v[finite], spec["angle_unit"], MIN_POINTS)
    if found is not None:
        r, c, why = found
        raise IngestError(why, file=rows.path, row=None if r is None else rows.lines[finite[r]], column=headers[c])


def pose_groups(rows: Rows) -> dict:
    """A target's file: id -> its usable marker rows (row indices), every id of the file in order of
    first appearance (an id whose rows all failed their checks: none)."""
    out = {pid: [] for pid in rows.first_rows()}
    for r, (pid, p) in enumerate(zip(rows.ids, rows.problem)):
        if p is None:
            out[pid].append(r)
    return out


def target_geometry(target, points: dict, rows: Rows, limit: float) -> tuple[dict, str]:
    """The target's geometry {name: (3,) mm}: ingest.target's (every marker of the file in it), else
    estimated from the poses' markers (orientation.estimate_geometry) -> (geometry, "given" | "estimated")."""
    if target is None:
        try:
            return orientation.estimate_geometry(list(points.values())), "estimated"
        except ValueError as e:
            seen = Counter(name for p in points.values() for name in p)
            rare = min(seen, key=seen.get)                  # the marker fewest poses hold: a mislabelled row?
            lines = [rows.lines[r] for r, (name, p) in enumerate(zip(rows.markers, rows.problem))
                     if name == rare and p is None] if seen[rare] < len(points) else []
            hint = (f"; marker {rare!r} is in {seen[rare]} of {len(points)} poses (row(s) "
                    f"{', '.join(map(str, lines[:5]))}{', ...' if len(lines) > 5 else ''}): mislabelled?" if lines else "")
            raise IngestError(f"{e}{hint}: the target's geometry is estimated from the first pose with every marker; "
                              "give it in ingest.target", file=rows.path, row=lines[0] if lines else None,
                              column=rows.groups["marker"][0]) from None
    geometry = {str(k): np.asarray(v, float) for k, v in target["markers"].items()}
    if orientation.collinear(geometry):
        raise IngestError("ingest.target.markers: the markers lie on a line; a rigid target needs three "
                          "not on one line", file="params.yaml")
    for r, (name, p) in enumerate(zip(rows.markers, rows.problem)):
        if p is None and name not in geometry:
            raise IngestError(f"marker {name!r} is not in ingest.target.markers ({', '.join(geometry)})",
                              file=rows.path, row=rows.lines[r], column=rows.groups["marker"][0])
    why = orientation.geometry_problem(geometry, list(points.values()), limit)
    if why:
        raise IngestError(f"ingest.target.markers do not fit the markers measured in {rows.path}: {why}",
                          file="params.yaml")
    return geometry, "given"


def pose_extras(rows: Rows, groups: list) -> list:
    """The target file's other columns, one cell per pose: those on which every pose's marker rows agree
    (a time stamp); one that differs between a pose's markers (per-marker values) is left out."""
    out = []
    for header, cells in rows.extras:
        per_pose = [{cells[r].strip() for r in idx} for idx in groups]
        if all(len(c) <= 1 for c in per_pose):
            out.append((header, [next(iter(c), "") for c in per_pose]))
        else:
            log.info("column %r of %s differs between one pose's markers: left out of the ingest table",
                     header, rows.path)
    return out


def fit_target_pose(rows: Rows, idx: list, points: dict, geometry: dict, limit: float):
    """One pose's markers (rows idx, positions `points` {name: (3,) mm}) fitted to the geometry ->
    (orientation.PoseFit, the file lines of the markers kept, a `marker_residual` entry for each marker off
    the fit)."""
    fit = orientation.fit_pose(geometry, points, limit)
    row_of = {rows.markers[r]: r for r in idx}
    off = [entry(rows, row_of[name], "marker_residual", f"marker {name!r} is {res:.3g} mm off its pose's fit "
                 f"to the target (limit {limit:g} mm, ingest.target_residual_mm)") for name, res in fit.removed]
    gone = {name for name, _ in fit.removed}
    return fit, [rows.lines[r] for r in idx if rows.markers[r] not in gone], off


def target_rows(rows: Rows, cfg: dict) -> tuple[Rows, dict, list]:
    """A multi-marker target's rows (several per id, one per marker) -> one row per pose: the target
    frame's origin (values, in the file's length unit) and rotation (quat), fitted to the target's
    geometry (lib/reading/orientation.py); a pose left with fewer than 3 markers has `too_few_markers`. Returns
    (pose rows, the summary's `target`, the markers dropped off their pose's fit)."""
    scale = 1000.0 if cfg["length_unit"] == "m" else 1.0
    groups = pose_groups(rows)
    points = {pid: {rows.markers[r]: rows.values[r, :3] * scale for r in idx} for pid, idx in groups.items()}
    limit = float(cfg["target_residual_mm"])
    geometry, source = target_geometry(cfg["target"], points, rows, limit)
    fitted = [fit_target_pose(rows, idx, points[pid], geometry, limit) for pid, idx in groups.items()]
    fits, off = [(f, lines) for f, lines, _ in fitted], [e for *_, gone in fitted for e in gone]
    ok = [f.R is not None for f, _ in fits]
    values = np.array([f.t / scale if good else [np.nan] * 3 for (f, _), good in zip(fits, ok)]).reshape(-1, 3)
    quat = np.array([orientation.quaternion(f.R) if good else [np.nan] * 4
                     for (f, _), good in zip(fits, ok)]).reshape(-1, 4)
    problem = [None if good else ("too_few_markers", f.why + (f" ({len(f.removed)} off the fit)" if f.removed else ""),
                                  None) for (f, _), good in zip(fits, ok)]
    failed = {}                                      # poses none of whose rows passed: their rows' own reasons
    for i, (pid, idx) in enumerate(groups.items()):
        if not idx:
            own = [r for r, rid in enumerate(rows.ids) if rid == pid]
            failed[i] = [rows.lines[r] for r in own]
            problem[i] = (", ".join(dict.fromkeys(rows.problem[r][0] for r in own)), "no usable marker row", None)
    first = rows.first_rows()
    pose = Rows(rows.path, rows.role, [rows.lines[first[pid]] for pid in groups], list(groups), values, problem,
                rows.headers, pose_extras(rows, list(groups.values())), rows.sep, rows.decimal,
                groups=rows.groups, quat=quat, members=[lines for _, lines in fits], n_lines=rows.n_read,
                failed=failed)
    residuals = [v for f, _ in fits for v in f.residual.values()]
    info = {"marker_column": rows.groups["marker"][0], "geometry": source,
            "origin": "ingest.target's origin" if source == "given" else "the markers' centroid",
            "markers_mm": {name: np.asarray(g).tolist() for name, g in geometry.items()},
            "residual_limit_mm": limit, "n_poses_fitted": int(sum(ok)),
            "residual_mm": {"median": float(np.median(residuals)) if residuals else None,
                            "max": float(np.max(residuals)) if residuals else None}}
    return pose, info, off


def orientation_units(cfg: dict, files: list, target: dict | None) -> dict | None:
    """units.orientation of the summary: where the meas_q* columns came from; None without them."""
    to = "meas_qw, meas_qx, meas_qy, meas_qz: unit quaternion (w >= 0) of the probe -> tracker rotation"
    if target is not None:
        return {"kind": "target", "marker_column": target["marker_column"], "to": to}
    headers = files[-1].groups.get("orientation")
    if not headers:
        return None
    spec = cfg["orientation"]
    keys = {"euler": ("sequence", "angle_unit"), "quaternion": ("scalar_first",), "matrix": ()}[spec["kind"]]
    return {"columns": headers, "kind": spec["kind"], **{k: spec[k] for k in keys}, "to": to}


# -------------------------------------------------------------------- points

@dataclass
class Points:
    """Paired points: ids, angles (deg), positions (mm), orientations, and their source rows per file."""
    ids: np.ndarray                 # (n,) str
    q: np.ndarray                   # (n, 6) degrees
    m: np.ndarray                   # (n, 3) mm
    src: dict                       # role -> (Rows, (n,) row indices)
    o: np.ndarray | None = None     # (n, 4) unit quaternions w, x, y, z (the probe -> tracker), or None
    dropped: tuple = ()             # the `dropped` entries of every row read and not among these points

    def __len__(self):
        return len(self.ids)

    def drop(self, mask: np.ndarray, reason: str, details: list, named: str | None = None) -> "Points":
        """Points without `mask`, each dropped point's rows added to `dropped`. named: the role whose cells
        the details name; the point's row in another file says where they are."""
        def detail(role: str, k: int) -> str:
            if named not in self.src or role == named:
                return details[k]
            rows, idx = self.src[named]
            return f"its {named} row {rows.lines[idx[k]]} in {rows.path}: {details[k]}"
        gone = tuple(e for k in np.flatnonzero(mask) for role, (rows, idx) in self.src.items()
                     for e in entries(rows, idx[k], reason, detail(role, k), self.ids[k]))
        keep = ~np.asarray(mask)
        return Points(self.ids[keep], self.q[keep], self.m[keep],
                      {role: (rows, idx[keep]) for role, (rows, idx) in self.src.items()},
                      None if self.o is None else self.o[keep], self.dropped + gone)


def entry(rows: Rows, r: int, reason: str, detail: str, pid=None, line=None) -> dict:
    """One line of reports/ingest.json `dropped` (row r's own file line, unless `line` says)."""
    return {"point_id": str(pid if pid is not None else rows.ids[r]), "file": rows.path,
            "row": int(rows.lines[r] if line is None else line), "reason": reason, "detail": detail}


def entries(rows: Rows, r: int, reason: str, detail: str, pid=None) -> list:
    """`entry` for every file line row r stands for (a target's pose: its marker rows)."""
    return [entry(rows, r, reason, detail, pid, line) for line in rows.lines_of(r)]


def row_problems(rows: Rows) -> list:
    """Dropped entries for the rows that failed their own checks."""
    return [e for r, p in enumerate(rows.problem) if p for e in entries(rows, r, p[0], p[1])]


def make_points(pairs: list, joints: Rows, tracker: Rows | None, dropped: list) -> Points:
    """Points from (joint row, tracker row) index pairs, the rows left out listed in `dropped`; tracker
    None: positions are in `joints`."""
    j = np.array([a for a, _ in pairs], dtype=int)
    ids = np.array([joints.ids[r] for r in j], dtype=object)
    if tracker is None:
        o = None if joints.quat is None else joints.quat[j]
        return Points(ids, joints.values[j, :6], joints.values[j, 6:9], {"table": (joints, j)}, o, tuple(dropped))
    t = np.array([b for _, b in pairs], dtype=int)
    o = None if tracker.quat is None else tracker.quat[t]
    return Points(ids, joints.values[j, :6], tracker.values[t, :3], {"joints": (joints, j), "tracker": (tracker, t)},
                  o, tuple(dropped))


def pair_by_id(J: Rows, T: Rows) -> tuple[list, list]:
    """(joint row, tracker row) pairs with the same id, and the entries of the rows left unpaired."""
    jfirst, tfirst = J.first_rows(), T.first_rows()
    if not set(jfirst) & set(tfirst):
        show = lambda ids: ", ".join(list(ids)[:4]) + (" ..." if len(ids) > 4 else "")
        raise IngestError(f"no point ids in common with {J.path} (ids there: {show(jfirst) or 'none'}; "
                          f"here: {show(tfirst) or 'none'}); are the right two files paired?",
                          file=T.path)
    pairs, dropped = [], []
    for A, B, other, from_joints in ((J, T, tfirst, True), (T, J, jfirst, False)):
        for r, pid in enumerate(A.ids):
            if A.problem[r]:
                continue
            o = other.get(pid)
            if o is None:
                dropped += entries(A, r, "unpaired", f"id {pid!r} is not in {B.path}")
            elif B.problem[o]:
                lines = B.lines_of(o) or B.failed.get(o) or [B.lines[o]]
                which = f"row {lines[0]}" if len(lines) == 1 else f"rows {', '.join(map(str, lines))}"
                dropped += entries(A, r, "partner_dropped", f"its {which} in {B.path} "
                                   f"{'was' if len(lines) == 1 else 'were'} dropped ({B.problem[o][0]})")
            elif from_joints:
                pairs.append((r, o))
    return pairs, dropped


def pair_by_order(J: Rows, C: Rows) -> tuple[list, list]:
    """The i-th point with the i-th joint row (the counts must match), and the entries of the rows whose
    partner was dropped."""
    if len(C.lines) != len(J.lines):
        raise IngestError(f"{len(C.lines)} points but {len(J.lines)} joint rows in {J.path}; a point "
                          "cloud is paired with the joint rows by order, so the counts must match",
                          file=C.path)
    C.ids = list(J.ids)
    pairs, dropped = [], []
    for r in range(len(J.lines)):
        jp, cp = J.problem[r], C.problem[r]
        if jp is None and cp is None:
            pairs.append((r, r))
        elif jp is None:
            dropped.append(entry(J, r, "partner_dropped",
                                 f"point {r + 1} in {C.path} was dropped ({cp[0]})"))
        elif cp is None:
            dropped.append(entry(C, r, "partner_dropped",
                                 f"its row {J.lines[r]} in {J.path} was dropped ({jp[0]})"))
    return pairs, dropped


# -------------------------------------------------------------------- checks

def drop_joint_limits(pts: Points, robot, headers: list) -> Points:
    """Drop points with an angle outside the robot's limits (stop if most are: unit error)."""
    out = robot.check_joints(pts.q)
    bad = out.any(axis=1)
    if 2 * bad.sum() > len(pts) > 0:
        k = int(np.flatnonzero(bad)[0])
        rows, idx = next(iter(pts.src.values()))
        j = int(np.flatnonzero(out[k])[0])
        raise IngestError(f"{int(bad.sum())} of {len(pts)} points have joint angles outside the "
                          f"{robot.name} limits (e.g. {pts.q[k, j]:.6g} deg): degrees read as "
                          "radians? check ingest.angle_unit", file=rows.path,
                          row=rows.lines[idx[k]], column=headers[j])
    details = [""] * len(pts)
    for k in np.flatnonzero(bad):
        details[k] = "; ".join(f"column '{headers[i]}' = {pts.q[k, i]:.6g} deg outside "
                               f"[{robot.limits_deg[i, 0]:g}, {robot.limits_deg[i, 1]:g}]"
                               for i in np.flatnonzero(out[k]))
    return pts.drop(bad, "joint_limit", details, "joints")


def check_count(pts: Points, path: str) -> None:
    if len(pts) < MIN_POINTS:
        raise IngestError(f"only {len(pts)} points left after dropping {len(pts.dropped)} rows "
                          f"(need at least {MIN_POINTS}); see the reasons above or in "
                          f"reports/ingest.json: {dict(Counter(d['reason'] for d in pts.dropped))}", file=path)


def drop_position_outliers(pts: Points, robot, headers: list) -> Points:
    """Drop points farther than POSITION_FAR x (reach + |tool|) from the median position (a typo);
    none if more than half are (a unit error: check_scale judges it)."""
    dev = pts.m - np.median(pts.m, axis=0)
    dist = np.linalg.norm(dev, axis=1)
    limit = POSITION_FAR * (robot.reach + float(np.linalg.norm(robot.tool)))
    bad = dist > limit
    if 2 * bad.sum() > len(pts):
        return pts
    details = [position_detail(pts.m[k], dev[k], limit, headers) if b else "" for k, b in enumerate(bad)]
    return pts.drop(bad, "position_outlier", details, "tracker")


def position_detail(m: np.ndarray, dev: np.ndarray, limit: float, headers: list) -> str:
    """The columns that put a point far off (those at least half as far off as the farthest)."""
    off = np.flatnonzero(np.abs(dev) >= np.abs(dev).max() / 2)
    cells = ", ".join(f"column '{headers[i]}' = {m[i]:.6g} mm" for i in off)
    return (f"{cells}: {np.linalg.norm(dev):.4g} mm from the median position, limit {limit:.4g} mm "
            f"({POSITION_FAR:g} x the robot's reach + tool; a lost decimal point?)")


def check_scale(pts: Points, robot, length_unit: str, headers: list, path: str) -> float:
    """Stop if the positions' extent does not fit the robot's reach; returns the extent (mm)."""
    extent = float(np.linalg.norm(np.ptp(pts.m, axis=0)))
    lo, hi = robot.reach / SCALE_RANGE, robot.reach * SCALE_RANGE
    cols = ", ".join(headers)
    if 0 < extent < lo:
        guess = "these look like metres: set ingest.length_unit: m" if length_unit == "mm" \
            else "implausibly small: check the columns and ingest.length_unit"
        raise IngestError(f"positions ({cols}, read as {length_unit}) span only {extent:.4g} mm but a "
                          f"{robot.name} reaches ~{robot.reach:.0f} mm: {guess} "
                          "(a scale that looks wrong is an error, not a guess)", file=path)
    if extent > hi:
        guess = "these look like millimetres: set ingest.length_unit: mm" if length_unit == "m" \
            else "implausibly large: check the columns and ingest.length_unit"
        raise IngestError(f"positions ({cols}, read as {length_unit}) span {extent:.4g} mm but a "
                          f"{robot.name} reaches ~{robot.reach:.0f} mm: {guess} "
                          "(a scale that looks wrong is an error, not a guess)", file=path)
    return extent


def looks_like_radians(q_deg: np.ndarray) -> bool:
    """Every angle, read as degrees, within +-2*pi: they are radians (no real pose set is that small)."""
    return len(q_deg) > 0 and np.abs(q_deg).max() <= 2 * np.pi + 1e-9


def check_angle_scale(pts: Points, units: list, headers: list, path: str) -> None:
    """Stop if every degree-read angle lies within +-2*pi: they are radians."""
    deg = [i for i, u in enumerate(units) if u == "deg"]
    if len(deg) == 6 and len(pts) >= MIN_POINTS and looks_like_radians(pts.q):
        named = [h for h in headers if h.strip().lower().endswith("_deg")]      # the header, not the setting, says deg
        fix = (f"their headers say degrees ({', '.join(named)}): name them j1_rad .. j6_rad" if named
               else "set ingest.angle_unit: rad")
        raise IngestError(f"every joint angle ({', '.join(headers)}), read as degrees, lies within "
                          f"+-6.29: these look like radians; {fix}", file=path)


def reference_points(n: int) -> np.ndarray:
    """The gross-outlier check's reference points (indices, ascending): every point when n <=
    REFERENCE_POINTS, else REFERENCE_POINTS of them drawn without replacement (seed REFERENCE_SEED)."""
    if n <= REFERENCE_POINTS:
        return np.arange(n)
    return np.sort(np.random.default_rng(REFERENCE_SEED).choice(n, REFERENCE_POINTS, replace=False))


def distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(c, 3), (r, 3) -> (c, r) Euclidean distances, summed x, y, z in that order (as np.linalg.norm)."""
    d = np.square(a[:, None, 0] - b[None, :, 0])
    d += np.square(a[:, None, 1] - b[None, :, 1])
    d += np.square(a[:, None, 2] - b[None, :, 2])
    return np.sqrt(d, out=d)


def consistency_scores(m: np.ndarray, t: np.ndarray, chunk: int = 128) -> np.ndarray:
    """Per point i: median over the reference points j != i (`reference_points`: all of them up to
    REFERENCE_POINTS) of | |m_i - m_j| - |t_i - t_j| | (mm); m, t (n, 3). Chunks of `chunk` points,
    one log line per PROGRESS_POINTS points scored when the references are a subset."""
    n = len(m)
    ref = reference_points(n)
    col = np.full(n, -1)
    col[ref] = np.arange(len(ref))                          # (n,) each point's column among the references
    mr, tr = m[ref], t[ref]                                 # (r, 3)
    out = np.empty(n)
    t0, shown = time.perf_counter(), 0
    for a in range(0, n, chunk):
        b = min(a + chunk, n)
        e = distances(m[a:b], mr)
        e -= distances(t[a:b], tr)
        np.abs(e, out=e)                                    # (c, r)
        own = np.flatnonzero(col[a:b] >= 0)
        e[own, col[a:b][own]] = np.inf                      # not against itself: sorted last, left out
        for rows, k in ((own, len(ref) - 1), (np.flatnonzero(col[a:b] < 0), len(ref))):
            if len(rows):                                   # the median of the k smallest of each row
                lo, hi = (k - 1) // 2, k // 2
                part = e if len(rows) == b - a else e[rows]
                part.partition(hi, axis=1)                  # one selection, then the max below it
                lower = part[:, hi] if lo == hi else part[:, :hi].max(axis=1)
                out[a + rows] = (lower + part[:, hi]) / 2
        if n > REFERENCE_POINTS and (b - shown >= PROGRESS_POINTS or b == n):
            shown = b
            log.info("gross-outlier check: %d of %d points scored against %d reference points (%.0f s)",
                     b, n, len(ref), time.perf_counter() - t0)
    return out


def nominal_positions(q_deg: np.ndarray, robot, chunk: int = 32768) -> np.ndarray:
    """Nominal FK with tool, (n, 6) deg -> (n, 3) mm, `chunk` poses at a time (FK's intermediates are
    large)."""
    return np.concatenate([fk_numpy(q_deg[a:a + chunk], robot) for a in range(0, len(q_deg), chunk)] or
                          [np.empty((0, 3))])


def drop_gross_outliers(pts: Points, robot, limit, path: str):
    """Drop points whose distances to the others disagree with nominal FK by more than `limit` mm."""
    if limit is None:
        return pts, None
    s = consistency_scores(pts.m, nominal_positions(pts.q, robot))
    bad = s > float(limit)
    info = {"limit_mm": float(limit), "median_mm": float(np.median(s)), "max_mm": float(s.max()),
            "n_dropped": int(bad.sum())}
    if len(pts) > REFERENCE_POINTS:                         # scored against a subset (reference_points)
        info["reference_points"] = REFERENCE_POINTS
    if 2 * bad.sum() > len(pts):
        raise IngestError(f"{int(bad.sum())} of {len(pts)} points fail the distance check against nominal "
                          f"{robot.name} kinematics (median disagreement {np.median(s):.1f} mm > "
                          f"gross_outlier_mm {limit:g}): robot model, tool_mm, angle or length units "
                          "probably don't match the measurements", file=path)
    details = [f"distances to the other points disagree with nominal FK by {v:.2f} mm (median), "
               f"limit {float(limit):g} mm" if b else "" for v, b in zip(s, bad)]
    return pts.drop(bad, "gross_outlier", details), info


def check_geometry(pts: Points, path: str) -> dict:
    """Stop if the measured points are (nearly) collinear; flag them if (nearly) coplanar."""
    sv = np.linalg.svd(pts.m - pts.m.mean(axis=0), compute_uv=False) / np.sqrt(len(pts))
    if sv[0] == 0:
        raise IngestError(f"all {len(pts)} measured points are the same point", file=path)
    if sv[1] < FLAT_RATIO * sv[0]:
        raise IngestError(f"the {len(pts)} measured points lie on a line (spread {sv[0]:.3g} mm along it, "
                          f"{sv[1]:.3g} mm across): no frame can be fitted", file=path)
    coplanar = bool(sv[2] < FLAT_RATIO * sv[0])
    if coplanar:
        log.warning("the measured points are nearly coplanar (spread %.3g mm off the plane)", sv[2])
    return {"spread_mm": sv.tolist(), "coplanar": coplanar}


# -------------------------------------------------------------------- output

def numeric_or_text(cells: list, decimal: str):
    """A column as floats if every cell is a number (or empty/NaN), else as stripped text."""
    values = []
    for c in cells:
        v, err = parse_number(c, decimal)
        if err and err[0] == "non_numeric":
            return [c.strip() for c in cells]
        values.append(v)
    return np.array(values, dtype=float)


def extra_columns(pts: Points) -> dict:
    """The inputs' other columns, for the kept points, under unique names."""
    taken, out = {"point_id", *JOINTS_DEG, *MEAS, *MEAS_Q, CAMPAIGN, STATION}, {}   # the ingest table's own
    for role, (rows, idx) in pts.src.items():
        for header, cells in rows.extras:
            name = header if header not in taken else f"{role}_{header}"
            k = 2
            while name in taken:
                name, k = f"{role}_{header}_{k}", k + 1
            taken.add(name)
            out[name] = numeric_or_text([cells[r] for r in idx], rows.decimal)
    return out


def to_frame(pts: Points) -> pd.DataFrame:
    df = pd.DataFrame({"point_id": [str(p) for p in pts.ids]})
    for i, c in enumerate(JOINTS_DEG):
        df[c] = pts.q[:, i].astype(np.float64)
    for i, c in enumerate(MEAS):
        df[c] = pts.m[:, i].astype(np.float64)
    for i, c in enumerate(MEAS_Q if pts.o is not None else []):
        df[c] = pts.o[:, i].astype(np.float64)
    for name, col in extra_columns(pts).items():
        df[name] = col
    return df


def file_info(rows: Rows) -> dict:
    return {"path": rows.path, "sep": rows.sep, "decimal": rows.decimal if rows.sep else None,
            "columns": rows.headers, "n_rows": rows.n_read}


# -------------------------------------------------------------------- settings and the whole read

def settings(ingest_cfg: dict) -> dict:
    """The `ingest:` section, checked (keys, separators, units), `table` set when both inputs are one file."""
    cfg = dict(check_keys(ingest_cfg, "ingest"))
    check_values(cfg, "ingest")
    for sub in ("columns", "orientation"):
        check_values(check_keys(cfg[sub], f"ingest.{sub}"), f"ingest.{sub}")
    check_orientation_settings(cfg)
    cfg["table"] = cfg["joints"] if str(cfg["joints"]) == str(cfg["tracker"]) else None
    if cfg["sep"] != "auto":
        cfg["sep"] = SEPARATORS[cfg["sep"]]
    return cfg


def check_orientation_settings(cfg: dict) -> None:
    """Stop on orientation settings that do not fit together (each one's values: config.RULES)."""
    cols, kind = cfg["columns"], cfg["orientation"]["kind"]
    need = orientation.KINDS[kind]
    if cols["orientation"] is not None and len(cols["orientation"]) != need:
        raise IngestError(f"ingest.columns.orientation has {len(cols['orientation'])} headers but "
                          f"ingest.orientation.kind {kind} reads {need} (euler 3, quaternion 4, matrix 9)",
                          file="params.yaml")
    if cols["orientation"] is not None and cols["marker"] is not None:
        raise IngestError("ingest.columns.orientation and ingest.columns.marker: a multi-marker target's "
                          "orientation comes from its markers; set one of the two", file="params.yaml")
    if cfg["target"] is not None and cols["marker"] is None:
        raise IngestError("ingest.target is a multi-marker target's geometry: set ingest.columns.marker "
                          "(the column naming each row's marker) too", file="params.yaml")


def id_settings(setting) -> tuple:
    """columns.point_id -> (joints header, tracker header)."""
    if isinstance(setting, (list, tuple)):
        if len(setting) != 2:
            raise IngestError("ingest.columns.point_id: one header, or [joints header, tracker header]",
                              file="params.yaml")
        return setting[0], setting[1]
    return setting, setting


def read_inputs(cfg: dict):
    """Read the configured files -> (points, [Rows], path named in whole-set errors, the summary's
    `target` or None)."""
    dropped = []
    cols = cfg["columns"]
    joint_group = (cols["joints"], AUTO_JOINTS, "joints")
    tracker_groups = [(cols["position"], AUTO_POSITION, "position")]
    if cols["orientation"] is not None:                    # explicit only: never guessed from headers
        tracker_groups.append((cols["orientation"], [cols["orientation"]], "orientation"))
    if cfg["table"]:
        if cols["marker"] is not None:
            raise IngestError("ingest.columns.marker: a multi-marker target has several rows per pose, so it "
                              "needs its own tracker file (ingest.tracker), paired by id", file="params.yaml")
        if isinstance(cols["point_id"], (list, tuple)):
            raise IngestError(f"ingest.columns.point_id: {list(cols['point_id'])} names a joints file's and a tracker "
                              f"file's id columns, but {cfg['table']} is one table of both: give its one header",
                              file="params.yaml")
        rows = read_rows(str(cfg["table"]), "table", cfg, cols["point_id"], [joint_group, *tracker_groups])
        add_orientation(rows, cfg["orientation"])
        dropped += row_problems(rows)
        pairs = [(r, r) for r, p in enumerate(rows.problem) if p is None]
        return make_points(pairs, rows, None, dropped), [rows], rows.path, None
    jid, tid = id_settings(cols["point_id"])
    J = read_rows(str(cfg["joints"]), "joints", cfg, jid, [joint_group])
    tracker, target = str(cfg["tracker"]), None
    if Path(tracker).suffix.lower() in CLOUD_SUFFIXES:
        if cols["orientation"] is not None or cols["marker"] is not None:
            key = "orientation" if cols["orientation"] is not None else "marker"
            raise IngestError(f"a point cloud holds positions only, no orientation or marker names: "
                              f"ingest.columns.{key} needs a tracker table (.csv/.txt)", file=tracker)
        T = read_cloud(tracker)
        dropped += row_problems(J)
        pairs, unpaired = pair_by_order(J, T)
        dropped += unpaired + row_problems(T)
    else:
        T = read_rows(tracker, "tracker", cfg, tid, tracker_groups, cols["marker"])
        add_orientation(T, cfg["orientation"])
        if cols["marker"] is not None:                      # marker rows -> one row per pose
            dropped += row_problems(T)
            T, target, off = target_rows(T, cfg)
            dropped += off
        pairs, unpaired = pair_by_id(J, T)
        dropped += unpaired + row_problems(J) + row_problems(T)
    return make_points(pairs, J, T, dropped), [J, T], T.path, target


def convert_units(pts: Points, joints: Rows, cfg: dict) -> list:
    """Angles to degrees (column by column), positions to mm; returns each joint column's unit."""
    units = [unit_of(h, cfg["angle_unit"]) for h in joints.headers[:6]]
    for i, u in enumerate(units):
        if u == "rad":
            pts.q[:, i] = np.degrees(pts.q[:, i])
    if cfg["length_unit"] == "m":
        pts.m *= 1000.0
    return units


def unit_of(header: str, setting: str) -> str:
    """A joint column's angle unit: its name's if it says (_rad, actual_q_, _deg), else the setting."""
    h = header.lower()
    if h.endswith("_rad") or h.startswith("actual_q_"):
        return "rad"
    if h.endswith("_deg"):
        return "deg"
    return setting


SETTING = re.compile(r"(?<![\w/.])ingest\.(?!json|parquet)(?=[a-z_])")    # a message's `ingest.<key>`, not a file


def ingest(ingest_cfg: dict, robot, key: str = "ingest"):
    """Read, pair, check and convert the inputs of the `ingest:` section for `robot` (robots.Robot)
    -> (table, summary). Writes nothing. key: where params.yaml gives these settings (a campaign's
    `campaigns.more.NAME.ingest`, merged over the section), which the errors name."""
    try:
        return read_campaign(ingest_cfg, robot)
    except IngestError as e:
        if key == "ingest":
            raise
        raise IngestError(SETTING.sub(f"{key}.", e.message), e.file, e.row, e.column) from None


def read_campaign(ingest_cfg: dict, robot):
    """ingest's work, its errors naming the `ingest:` section's keys."""
    cfg = settings(ingest_cfg)
    t0 = time.perf_counter()
    pts, files, path, target = read_inputs(cfg)
    if len(pts) > REFERENCE_POINTS:                         # a large campaign: say where it is
        log.info("read %s: %d points paired (%.0f s); checking them", ", ".join(f"{f.n_read} rows of {f.path}"
                                                                        for f in files), len(pts), time.perf_counter() - t0)
    joints, positions = files[0], files[-1]
    jh, ph = joints.groups["joints"], positions.groups["position"]
    units = convert_units(pts, joints, cfg)
    for h, u in zip(jh, units):
        if u != cfg["angle_unit"]:
            log.info("column %r is read in %s (its name says so), whatever angle_unit says", h, u)
    check_count(pts, path)
    check_angle_scale(pts, units, jh, joints.path)
    pts = drop_joint_limits(pts, robot, jh)
    check_count(pts, path)
    pts = drop_position_outliers(pts, robot, ph)
    check_count(pts, path)
    extent = check_scale(pts, robot, cfg["length_unit"], ph, positions.path)
    pts, outliers = drop_gross_outliers(pts, robot, cfg["gross_outlier_mm"], path)
    check_count(pts, path)
    geometry = {"extent_mm": extent, **check_geometry(pts, path)}

    order = {rows.path: i for i, rows in enumerate(files)}
    dropped = sorted(pts.dropped, key=lambda d: (order[d["file"]], d["row"]))
    summary = {
        "files": {rows.role: file_info(rows) for rows in files},
        "n_read": {rows.role: rows.n_read for rows in files},
        "n_kept": len(pts),
        "dropped": dropped,
        "dropped_counts": dict(Counter(d["reason"] for d in dropped)),
        "units": {"joints": {c: {"column": h, "unit": u} for c, h, u in zip(JOINTS_DEG, jh, units)},
                  "position": {"columns": ph, "unit": cfg["length_unit"],
                               "to_mm": 1000.0 if cfg["length_unit"] == "m" else 1.0}},
        "geometry": geometry,
        "gross_outlier": outliers,
    }
    rotation = orientation_units(cfg, files, target)
    if rotation is not None:                                # only then: a campaign without is as it was
        summary["units"]["orientation"] = rotation
    if target is not None:
        summary["target"] = target
    log_counts(summary, files)
    return to_frame(pts), summary


def log_counts(summary: dict, files: list) -> None:
    """One line: rows read per file, points kept, rows dropped per file by reason."""
    parts = []
    for rows in files:
        c = Counter(d["reason"] for d in summary["dropped"] if d["file"] == rows.path)
        why = " (" + ", ".join(f"{n} {r}" for r, n in c.most_common()) + ")" if c else ""
        parts.append(f"{rows.path}: read {rows.n_read}, dropped {sum(c.values())}{why}")
    log.info("%s; kept %d points", "; ".join(parts), summary["n_kept"])
