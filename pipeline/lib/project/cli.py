"""How a stage or a command starts and ends: the main of a stage, the option naming the project, and bad
input said in one line, no traceback.

    one_line(command, run, argv)   run(argv); a Refused exits 1, bad input (ValueError: IngestError,
                                   ParamsError; OSError) exits 2, each said in one message on stderr
    script(command, run)           one_line as a process's whole work (`python -m` a stage), its end
                                   without the collector's last sweep
    add_project(parser)            --project DIR: the project a command reads (its params.yaml and
                                   trained artifacts; default the working directory)
    stage_main(module, doc, run)   the main(argv=None, root=HERE) of a stage that takes no arguments:
                                   run(the params.yaml at root, root); module is the stage's
                                   __spec__.name (its import name, under python -m too)
"""
import argparse
import gc
import sys
from pathlib import Path

from pipeline.lib.project.artifacts import HERE, PARAMS_FILE
from pipeline.lib.project.config import load_params


class Refused(Exception):
    """What a command was asked cannot be done safely (waypoints that must not become moves, nothing to
    plan); the message says why."""


def one_line(command: str, run, argv=None):
    """run(argv), with bad input (exit 2) and a refusal (exit 1) said in one message, no traceback."""
    try:
        return run(argv)
    except Refused as e:
        print(f"{command}: refused: {e}", file=sys.stderr)
        raise SystemExit(1) from None
    except (ValueError, OSError) as e:                   # IngestError and ParamsError are ValueErrors
        print(f"{command}: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def script(command: str, run) -> None:
    """one_line(command, run) as the whole work of a process (`python -m pipeline.stages.<stage>`, as
    dvc.yaml runs it), which then ends with its objects frozen (gc.freeze), out of the collector's last
    sweep: ~0.4 s of every stage's ending, with torch loaded (docs/decisions.md). Never in a process that
    goes on: what it froze is never collected."""
    try:
        one_line(command, run)
    finally:
        gc.freeze()


def add_project(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--project", type=Path, default=HERE, metavar="DIR",
                    help="the project whose params.yaml and trained artifacts to use (default: the working directory)")


def stage_main(module: str, doc: str, run):
    """main(argv=None, root=HERE) of the stage `python -m module` (described by doc), which takes no
    arguments: run(load_params(root / params.yaml), root), returning what run returns."""
    def main(argv=None, root: Path = HERE):
        argparse.ArgumentParser(prog=f"python -m {module}", description=doc).parse_args(argv)
        return run(load_params(root / PARAMS_FILE), root)
    main.__doc__ = f"{module} on the project at `root` (its params.yaml); it takes no arguments."
    return main
