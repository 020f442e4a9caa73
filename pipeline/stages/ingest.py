"""Stage ingest: the tracker/controller exports -> data/interim/ingest.parquet (docs/data-format.md).

    python -m pipeline.stages.ingest                  dvc stage ingest: the ingest section's campaign,
                                               joined with every campaigns.more campaign
    python -m pipeline.stages.ingest campaign NAME    dvc stage ingest_campaign@NAME (foreach campaigns.more)

Reads `ingest.joints` and `ingest.tracker` (one table when both name the same
file); pairing, units, checks and the dropped-row list are lib/reading/readers.py's.
A `more` campaign is read the same way with its own overrides (lib/reading/campaigns.py)
into data/interim/campaigns/NAME.parquet and reports/campaigns/NAME.json.
Writes the table (with each point's campaign and station) and reports/ingest.json:
every dropped row, of every campaign, with its reason. Where the campaigns measure the probe's
orientation (meas_qw..meas_qz: all of them or none), those columns follow meas_z.
"""
import argparse
import hashlib
import json
from collections import Counter
from pathlib import Path

import pandas as pd

from pipeline.lib.project.artifacts import (CAMPAIGNS_DIR, CAMPAIGNS_REPORTS, HERE, INGEST_JSON,
                                            INGEST_TABLE, PARAMS_FILE, as_given, rooted_files)
from pipeline.lib.project.cli import script
from pipeline.lib.project.columns import CAMPAIGN, MEAS, MEAS_Q, STATION
from pipeline.lib.project.config import for_stage, load_params, logger, read_json, write_json
from pipeline.lib.project.writing import remove_stale
from pipeline.lib.reading.campaigns import (campaign_entry, campaign_ingest, campaign_stations, file_sha256,
                                            point_id)
from pipeline.lib.reading.readers import ingest
from pipeline.lib.robot.robots import load_robot

log = logger(__name__)
PARAMS = ("robot", "ingest", "campaigns")


def labelled(df: pd.DataFrame, campaign: str, station: str) -> pd.DataFrame:
    """df with its campaign and station columns (last)."""
    return df.assign(**{CAMPAIGN: campaign, STATION: station})


def joined(parts: list) -> pd.DataFrame:
    """The campaigns' tables as one; meas_q* (where the campaigns have them) right after meas_z. An extra column
    of numbers in one campaign and text in another is kept as text (parquet holds one type a column; before,
    the join stopped on pyarrow's "Could not convert", naming no campaign)."""
    kinds = {}
    for part in parts:
        for col in part.columns:
            kinds.setdefault(col, {})[part[CAMPAIGN].iloc[0] if len(part) else ""] = part[col].dtype.kind in "biuf"
    mixed = [c for c, k in kinds.items() if len(set(k.values())) > 1]
    for c in mixed:
        log.info("column %s: numbers in %s, text in %s: kept as text", c,
                 ", ".join(n for n, num in kinds[c].items() if num), ", ".join(n for n, num in kinds[c].items() if not num))
    parts = [p.astype({c: str for c in mixed if c in p.columns}) for p in parts]
    out = pd.concat(parts, ignore_index=True)
    if MEAS_Q[0] not in out.columns:
        return out
    rest = [c for c in out.columns if c not in MEAS_Q]
    k = rest.index(MEAS[-1]) + 1
    return out[rest[:k] + MEAS_Q + rest[k:]]


def one_target_frame(summaries: dict) -> None:
    """Stop when campaigns measuring orientation ({campaign: its ingest summary}) may not share the probe's
    frame: one of them estimated its multi-marker target's geometry from its own poses (ingest.target: null),
    whose frame (the markers' centroid, the tracker's axes at its first pose) is that campaign's alone."""
    oriented = [c for c, s in summaries.items() if "orientation" in s["units"]]
    estimated = [c for c in oriented if summaries[c].get("target", {}).get("geometry") == "estimated"]
    if len(oriented) < 2 or not estimated:
        return
    example = summaries[estimated[0]]["target"]["markers_mm"]
    markers = ", ".join(f"{n}: [{', '.join(f'{v:.3f}' for v in xyz)}]" for n, xyz in example.items())
    raise ValueError(f"campaigns {', '.join(oriented)} measure the probe's orientation, and {', '.join(estimated)} "
                     "estimated the multi-marker target's geometry from its own poses (ingest.target: null): each "
                     "estimate has its own frame (its markers' centroid, the tracker's axes at its first pose), so "
                     "the campaigns' orientations and positions would disagree by that frame. Give the target's "
                     f"geometry in ingest.target, e.g. campaign {estimated[0]}'s estimate: {{markers: {{{markers}}}}}")


def all_or_none_oriented(summaries: dict) -> None:
    """Stop when some campaigns ({campaign: its ingest summary}, the ingest section's first) measure the probe's
    orientation and others do not: the stages after ingest fit it from every point or from none (the frame
    stage stopped on the others' missing quaternions, naming no campaign)."""
    oriented = [c for c, s in summaries.items() if "orientation" in s["units"]]
    if not oriented or len(oriented) == len(summaries):
        return
    plain = [c for c in summaries if c not in oriented]
    key = lambda c: "ingest.columns.orientation" if c == next(iter(summaries)) else \
        f"campaigns.more.{c}.ingest.columns.orientation"
    raise ValueError(f"campaign(s) {', '.join(oriented)} measure the probe's orientation and {', '.join(plain)} "
                     "do not: the pipeline fits the orientation from every campaign or from none. Give "
                     f"{' and '.join(key(c) for c in plain)} (the headers of their orientation columns; or columns.marker, a "
                     "multi-marker target), or set "
                     f"{' and '.join(key(c) for c in oriented)} to null to calibrate on positions alone")


def read_as(cfg: dict, root: Path) -> str:
    """The SHA-256 of a campaign's ingest settings (its override merged over the section, as params.yaml gives
    them: the same wherever the project lies) and of its files' bytes (opened from root): what its table was
    read from."""
    files = {k: file_sha256(v) for k, v in rooted_files(cfg, root).items() if k in ("joints", "tracker")}
    return hashlib.sha256(json.dumps([cfg, files], sort_keys=True, default=str).encode()).hexdigest()


def run_campaign(params: dict, name: str, root: Path = HERE) -> dict:
    """Ingest one campaigns.more campaign; ids become NAME:id."""
    p = for_stage(params, PARAMS)
    station = campaign_entry(p["campaigns"], name)["station"]
    cfg = campaign_ingest(p["ingest"], p["campaigns"], name)
    df, summary = ingest(rooted_files(cfg, root), load_robot(p["robot"]), f"campaigns.more.{name}.ingest")
    summary = as_given(summary, cfg, root)
    summary["read_as"] = read_as(cfg, root)
    df["point_id"] = [point_id(name, p) for p in df["point_id"]]
    (root / CAMPAIGNS_DIR).mkdir(parents=True, exist_ok=True)
    labelled(df, name, station).to_parquet(root / CAMPAIGNS_DIR / f"{name}.parquet", index=False)
    write_json(root / CAMPAIGNS_REPORTS / f"{name}.json", {"campaign": name, "station": station, **summary})
    log.info("campaign %s (station %s): %d points", name, station, len(df))
    return summary


def run(params: dict, root: Path = HERE) -> dict:
    p = for_stage(params, PARAMS)
    stations = campaign_stations(p["campaigns"])
    first, *more = stations
    for folder, suffix in ((CAMPAIGNS_DIR, ".parquet"), (CAMPAIGNS_REPORTS, ".json")):
        for f in remove_stale(root / folder, more, (suffix,)):
            log.info("removed %s: campaign %r is no longer in campaigns.more", f, f.stem)
    df, summary = ingest(rooted_files(p["ingest"], root), load_robot(p["robot"]))
    for info in summary["files"].values():             # the campaign's identity (the twin's drive check)
        info["sha256"] = file_sha256(info["path"])
    summary = as_given(summary, p["ingest"], root)
    parts, reports = [labelled(df, first, stations[first])], {first: summary}
    summary["campaigns"] = {first: {"station": stations[first], "n_kept": len(df),
                                    "n_dropped": len(summary["dropped"])}}
    for name in more:
        path = root / CAMPAIGNS_DIR / f"{name}.parquet"
        if not path.exists():
            raise FileNotFoundError(f"{path}: campaign {name!r} (params.yaml campaigns.more) is not ingested; "
                                    f"run dvc repro, or python -m pipeline.stages.ingest campaign {name}")
        part, rep = pd.read_parquet(path), read_json(root / CAMPAIGNS_REPORTS / f"{name}.json")
        now = read_as(campaign_ingest(p["ingest"], p["campaigns"], name), root)
        if rep.get("read_as") != now:
            raise ValueError(f"{path}: campaign {name!r} was ingested from other settings or files than params.yaml's "
                             f"and its files' now; re-run python -m pipeline.stages.ingest campaign {name} (dvc repro "
                             "does)")
        if (part[STATION] != stations[name]).any():
            raise ValueError(f"{path}: ingested for station {part[STATION].iloc[0]!r}, params.yaml "
                             f"campaigns.more.{name}.station says {stations[name]!r}; re-run its ingest")
        parts.append(part)
        reports[name] = rep
        summary["dropped"] += [{**d, "campaign": name} for d in rep["dropped"]]
        summary["campaigns"][name] = {"station": stations[name], "n_kept": len(part),
                                      "n_dropped": len(rep["dropped"]), "files": rep["files"]}
    all_or_none_oriented(reports)
    one_target_frame(reports)
    out = joined(parts)
    if more:
        summary["n_kept"] = len(out)
        summary["dropped_counts"] = dict(Counter(d["reason"] for d in summary["dropped"]))
    (root / INGEST_TABLE).parent.mkdir(parents=True, exist_ok=True)
    out.to_parquet(root / INGEST_TABLE, index=False)
    write_json(root / INGEST_JSON, summary)
    log.info("wrote %s (%d rows: %s) and %s", root / INGEST_TABLE, len(out),
             ", ".join(f"{c} {v['n_kept']} (station {v['station']})" for c, v in summary["campaigns"].items()),
             root / INGEST_JSON)
    return summary


def main(argv=None, root: Path = HERE):
    ap = argparse.ArgumentParser(prog=f"python -m {__spec__.name}", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", nargs="?", choices=["campaign"], help="ingest one campaigns.more campaign")
    ap.add_argument("name", nargs="?")
    a = ap.parse_args(argv)
    if a.what == "campaign":
        if not a.name:
            ap.error("campaign: give its name (params.yaml campaigns.more)")
        return run_campaign(load_params(root / PARAMS_FILE), a.name, root)
    else:
        return run(load_params(root / PARAMS_FILE), root)


if __name__ == "__main__":
    script(__spec__.name, main)
