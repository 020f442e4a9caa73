"""The training campaigns (params.yaml `campaigns`): the ingest section's own, plus `more`.

Each campaign is read by the ingest rules with its own overrides of the ingest
section (as validate.campaigns are). Every table carries each point's
`campaign` and `station`; campaigns measured from one tracker placement share
a station, and so a base frame (the frame stage fits one per station). Points
of a `more` campaign get ids "<campaign>:<id>", unique across campaigns. The
first station (the ingest section's) is the one whose frame is reports/frame.json's
top-level R, t: the base frame everything downstream works in.
"""
import hashlib
import re
from pathlib import Path

from pipeline.lib.project.config import check_given, check_keys
from pipeline.lib.reading.presets import deep_merge

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")      # a campaign's name: it names its files


def file_sha256(path) -> str:
    """The SHA-256 of a file's bytes: a campaign's identity (ingest.json `files`, the twin's record)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def pair_sha256(joints, tracker) -> dict:
    """A campaign's identity from its two files (the same path twice for one table)."""
    return {"joints": file_sha256(joints), "tracker": file_sha256(tracker)}


def write_pair(folder, joints, tracker) -> dict:
    """A campaign's two tables written as the twin writes every campaign (docs/data-format.md): `folder`/
    joints.csv (6 decimals) and tracker.csv (4), LF line ends. Returns the ingest overrides naming them."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"joints": folder / "joints.csv", "tracker": folder / "tracker.csv"}
    joints.to_csv(paths["joints"], index=False, float_format="%.6f", lineterminator="\n")
    tracker.to_csv(paths["tracker"], index=False, float_format="%.4f", lineterminator="\n")
    return {k: str(p) for k, p in paths.items()}


def ingested_sha256(files: dict) -> dict:
    """The same identity from ingest.json's `files` (its "table" entry for one table)."""
    return {r: files[r if r in files else "table"]["sha256"] for r in ("joints", "tracker")}


def made_by_twin(record: dict, sha256: dict) -> str | None:
    """The name of the twin campaign ("main", "validation", "station_b") whose files have the SHA-256s
    `sha256` {"joints": .., "tracker": ..} (a campaign of one table: both the same), per the twin's
    record (twin.json); None: the twin did not make it."""
    made = {"main": record.get("campaign_sha256")} | {k: record[k].get("campaign_sha256")
                                                       for k in ("validation", "station_b") if k in record}
    return next((k for k, v in made.items() if v == sha256), None)


def named_campaign(campaigns: dict | None, name: str, where: str, keys: str) -> dict:
    """campaigns[name] (params.yaml `where`, e.g. validate.campaigns), its keys checked against the
    config section `keys`; its ingest overrides must name its files."""
    campaigns = campaigns or {}
    if name not in campaigns:
        raise ValueError(f"params.yaml {where}: no campaign {name!r}; have {sorted(campaigns)}")
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ValueError(f"params.yaml {where}: campaign name {name!r}: letters, digits, _ and - (it names the "
                         "campaign's files: data/interim/campaigns/NAME.parquet, reports/campaigns/NAME.json)")
    c = check_keys(campaigns[name], keys, f"{where}.{name}")       # named where it is given
    for key in ("joints", "tracker"):
        if key not in (c["ingest"] or {}):
            raise ValueError(f"params.yaml {where}.{name}.ingest: needs {key} (the campaign's file)")
    return c


def campaign_entry(campaigns: dict, name: str) -> dict:
    """campaigns.more[name] of the `campaigns:` section, checked (named_campaign) with a station name."""
    c = named_campaign(campaigns["more"], name, "campaigns.more", "campaigns.campaign")
    if not isinstance(c["station"], str) or not c["station"]:
        raise ValueError(f"params.yaml campaigns.more.{name}.station: a name, got {c['station']!r}")
    return c


def campaign_ingest(ingest: dict, campaigns: dict, name: str) -> dict:
    """The `ingest:` section overridden by campaign `name`'s (campaigns.more): `with_override`."""
    return with_override(ingest, campaign_entry(campaigns, name)["ingest"], f"campaigns.more.{name}.ingest")


def with_override(ingest: dict, override: dict, where: str) -> dict:
    """The `ingest:` section with a campaign's override (params.yaml `where`, e.g. campaigns.more.b.ingest)
    merged over it, its `target` replacing the section's whole (presets.REPLACED). The override's own keys
    and values are checked first, so that a bad one is named where it was given, not as the ingest section's."""
    check_given(override, "ingest", where)
    return deep_merge(ingest, override)


def campaign_stations(campaigns: dict) -> dict[str, str]:
    """{campaign: station} of the `campaigns:` section, the ingest section's campaign first."""
    out = {campaigns["name"]: campaigns["station"]}
    for name in campaigns["more"] or {}:
        if name in out:
            raise ValueError(f"params.yaml campaigns.more.{name}: the name of the ingest section's campaign "
                             f"(campaigns.name); choose another")
        out[name] = campaign_entry(campaigns, name)["station"]
    return out


def point_id(campaign: str, pid: str) -> str:
    """The id of a `more` campaign's point: unique across campaigns."""
    return f"{campaign}:{pid}"
