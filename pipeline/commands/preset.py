"""Command: merge a preset (data/presets/NAME.yaml) into params.yaml, print what changed.

    python -m pipeline.commands.preset gtpn-ur5 [--params params.yaml]

Merging and rendering are lib/reading/presets.py's (comments in params.yaml survive).
"""
import argparse

from pipeline.lib.project.cli import one_line
from pipeline.lib.reading.presets import REMOVED, apply_preset


def run(argv=None):
    ap = argparse.ArgumentParser(prog="python -m pipeline.commands.preset",
                                 description="Merge data/presets/NAME.yaml into params.yaml.")
    ap.add_argument("name", help="preset name (data/presets/NAME.yaml) or a YAML path")
    ap.add_argument("--params", default="params.yaml", help="params file to update (default params.yaml)")
    args = ap.parse_args(argv)
    diff = apply_preset(args.name, args.params)
    for key, old, new in diff:
        print(f"{key}: {old!r} removed" if new is REMOVED else f"{key}: {old!r} -> {new!r}")
    print(f"{args.params}: {len(diff)} setting(s) changed by preset {args.name}")


def main(argv=None):
    return one_line("pipeline.commands.preset", run, argv)     # a bad name or path: one line, no traceback


if __name__ == "__main__":
    main()
