"""Stage ingest: the tracker/controller exports -> data/interim/ingest.parquet (DATA_FORMAT.md).

Reads `ingest.joints` and `ingest.tracker` (one table when both name the same
file); pairing, units, checks and the dropped-row list are lib/readers.py's.
Writes the table and reports/ingest.json (every dropped row with its reason).
"""
from .lib.artifacts import INGEST_JSON, INGEST_TABLE
from .lib.config import load_params, logger, sections, write_json
from .lib.readers import ingest

log = logger(__name__)


def run(params: dict) -> dict:
    sections(params, "robot", "ingest")
    df, summary = ingest(params)
    INGEST_TABLE.parent.mkdir(parents=True, exist_ok=True)
    df.to_parquet(INGEST_TABLE, index=False)
    write_json(INGEST_JSON, summary)
    log.info("wrote %s (%d rows) and %s", INGEST_TABLE, len(df), INGEST_JSON)
    return summary


if __name__ == "__main__":
    run(load_params())
