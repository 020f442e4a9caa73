"""Command: regenerate the twin's default campaign, data/raw/{joints.csv, tracker.csv, twin.json}.

    python -m pipeline.commands.twin

Byte for byte the committed files (a test checks it); the twin itself is lib/sim/twin.py, its files lib/sim/twin_files.py.
"""
import argparse

from pipeline.lib.project.config import for_stage, load_params, logger
from pipeline.lib.sim.twin import RAW, SEED
from pipeline.lib.sim.twin_files import generate

log = logger(__name__)
PARAMS = ("frame", "split", "calibrate")        # its difficulty is measured the pipeline's way


def run(params: dict) -> dict:
    rec = generate(RAW, SEED, for_stage(params, PARAMS))
    d = rec["difficulty"]
    log.info("twin seed %d: wrote %s; noise floor %.4f mm; nominal DH after frame %.3f mm mean; "
             "classical fit %.3f mm mean (test; rigid DH %.3f); misreads %s", SEED, RAW, rec["noise_floor_mm"],
             d["nominal_after_frame_mean_mm"], d["classical_fit_mean_mm"]["test"], d["rigid_fit_mean_mm"]["test"],
             list(rec["misreads"]))
    return rec


def main(argv=None):
    argparse.ArgumentParser(prog="python -m pipeline.commands.twin", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter).parse_args(argv)
    run(load_params())


if __name__ == "__main__":
    main()
