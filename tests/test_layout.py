"""The architecture, checked. pipeline/ holds three packages and nothing else: the stages
(pipeline/stages/, exactly the modules ./dvc.yaml runs), the commands (pipeline/commands/, run by hand)
and the library (pipeline/lib/, one package per topic). The library imports only
itself; a stage imports only the library; a command (a module, or a package such as pipeline/commands/bench/)
only the library and its own modules: no stage or command imports another. Every stage's dvc.yaml deps
cover exactly the project code it runs and its params exactly the sections it reads (the opt-in
ablation/dvc.yaml's too, whose stages run a command); every command has a [project.scripts] entry."""
import ast
import importlib
import inspect
import json
import os
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml

from pipeline import stages
from pipeline.lib.project.artifacts import (FRAME_JSON, INGEST_TABLE, PARAMS_FILE, POINTS_TABLE, SPLIT_JSON,
                                            SPLIT_TABLE, THEORY_JSON)
from pipeline.lib.project.config import for_stage, load_params

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "pipeline"


def module_path(name: str) -> Path:
    """pipeline.lib.learning.model -> pipeline/lib/learning/model.py (a package -> its __init__.py)."""
    p = ROOT.joinpath(*name.split("."))
    return p / "__init__.py" if p.is_dir() else p.with_suffix(".py")


def imports(name: str) -> set[str]:
    """Project modules `name` imports directly, anywhere in the file (function-local too)."""
    path = module_path(name)
    pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "pipeline"}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            if base.split(".")[0] != "pipeline":
                continue
            for a in node.names:           # `from . import x` imports a module; `from .x import f` a name
                sub = f"{base}.{a.name}"
                out.add(sub if module_path(sub).exists() else base)
    return out


def closure(name: str) -> set[str]:
    """`name`, every project module it imports transitively, and the packages they sit in."""
    seen, todo = set(), [name]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        parts = m.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]    # importing a.b.c runs a, a.b
        todo += imports(m)
    return seen


DVC_FILES = ["dvc.yaml", "ablation/dvc.yaml"]      # the pipeline and the opt-in ablation (wdir: ..)


def dvc_stages() -> dict:
    """{stage name: stage} of every dvc.yaml (ablation stages as "ablation/<name>")."""
    out = {}
    for f in DVC_FILES:
        for name, stage in yaml.safe_load((ROOT / f).read_text())["stages"].items():
            out[name if f == "dvc.yaml" else f"{Path(f).parent}/{name}"] = stage
    return out


def stage_module(stage: dict) -> str:
    cmd = stage.get("do", stage)["cmd"].split()                 # a foreach stage keeps it under `do`
    assert cmd[:2] == ["python", "-m"], stage["cmd"]
    return cmd[2]


def foreach_keys(stage: dict, params: dict) -> list:
    """The keys a foreach stage (foreach: ${section.key} of params.yaml) runs for; [None] otherwise."""
    if "foreach" not in stage:
        return [None]
    node = params
    for part in stage["foreach"].strip("${}").split("."):
        node = node[part]
    return list(node or {})


def package_modules(folder: Path) -> list[str]:
    """Every module of the package in `folder` (its __init__ as the package's own name)."""
    out = []
    for p in sorted(folder.rglob("*.py")):
        parts = p.relative_to(ROOT).with_suffix("").parts
        out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


def top_level(kind: str) -> dict[str, list[str]]:
    """{pipeline.<kind>.<name>: its modules} for every module pipeline/<kind>/<name>.py and package
    pipeline/<kind>/<name>/: the stages (kind "stages") or the commands ("commands")."""
    folder = PKG / kind
    out = {f"pipeline.{kind}.{p.stem}": [f"pipeline.{kind}.{p.stem}"] for p in folder.glob("*.py")
           if p.stem != "__init__"}
    for d in folder.iterdir():
        if d.is_dir() and (d / "__init__.py").exists():
            out[f"pipeline.{kind}.{d.name}"] = package_modules(d)
    return out


STAGES = {name: stage_module(s) for name, s in dvc_stages().items()}           # ablation's too
PIPELINE = {stage_module(s) for s in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"].values()}
STAGE_MODULES, COMMAND_MODULES = top_level("stages"), top_level("commands")
CMDS = set(COMMAND_MODULES)
COMMANDS = {c.rsplit(".", 1)[1] for c in CMDS}
LIB = package_modules(PKG / "lib")
TOP = {**STAGE_MODULES, **COMMAND_MODULES}
MODULES = sorted((top, m) for top, mods in TOP.items() for m in mods)            # (its stage or command, module)


def test_every_stage_is_a_pipeline_module():
    """STAGES, which the deps and params tests below run over, holds every stage of every dvc.yaml that
    lists its code file by file (fleet/dvc.yaml depends on the whole package), each once under its own
    name (an ablation stage as ablation/<name>, so no stage hides another); ./dvc.yaml's stages run a
    stage module (pipeline/stages/<name>.py), ablation/dvc.yaml's a command."""
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "*dvc.yaml"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    by_file = {f: yaml.safe_load((ROOT / f).read_text())["stages"] for f in sorted(set(files))}
    whole = [f for f, stages in by_file.items() if all("pipeline" in s.get("do", s)["deps"] for s in stages.values())]
    assert sorted(DVC_FILES) == sorted(set(by_file) - set(whole)) and whole == ["fleet/dvc.yaml"]
    assert len(STAGES) == sum(len(by_file[f]) for f in DVC_FILES)          # none lost, none under another's name
    for f in DVC_FILES:
        for name, stage in by_file[f].items():
            key = name if f == "dvc.yaml" else f"{Path(f).parent}/{name}"
            cmd = stage.get("do", stage)["cmd"]
            assert STAGES[key] == cmd.split()[2] and module_path(STAGES[key]).is_file(), f"{f}: {name}: {cmd}"
            want = "a command" if f != "dvc.yaml" else "a stage module, not a command"
            assert STAGES[key] in TOP and (STAGES[key] in CMDS) == (f != "dvc.yaml"), \
                f"{f}: stage {name} runs {STAGES[key]}: want {want}"
    assert {"ingest", "train", "report", "validate", "ablation/group"} <= set(STAGES)
    assert {"pipeline.stages.ingest", "pipeline.stages.train", "pipeline.stages.report"} <= set(STAGES.values())


def test_the_tree_is_stages_commands_and_the_library():
    """pipeline/ holds its __init__.py and three packages; pipeline/stages/ holds exactly the modules
    ./dvc.yaml runs; the library's modules sit in topic packages, none loose in pipeline/lib/."""
    assert {p.name for p in PKG.iterdir() if p.name != "__pycache__"} == {"__init__.py", "stages", "commands", "lib"}
    assert set(STAGE_MODULES) == PIPELINE, (f"in pipeline/stages/ but not run by dvc.yaml: "
                                            f"{sorted(set(STAGE_MODULES) - PIPELINE)}; run but absent: "
                                            f"{sorted(PIPELINE - set(STAGE_MODULES))}")
    assert all(len(mods) == 1 for mods in STAGE_MODULES.values()), "a stage is one module"
    assert {"pipeline.commands.bench", "pipeline.commands.bench.__main__", "pipeline.commands.bench.real"} <= {m for _, m in MODULES}
    loose = sorted(p.name for p in (PKG / "lib").glob("*.py") if p.name != "__init__.py")
    assert not loose, f"pipeline/lib/{loose}: a library module outside a topic package"
    strays = [str(d.relative_to(PKG)) for d in PKG.rglob("*") if d.is_dir() and d.name != "__pycache__"
              and not (d / "__init__.py").exists() and any(d.glob("*.py"))]
    assert not strays, f"pipeline/{strays}: a folder of code that is not a package"


def test_the_runner_runs_every_stage_and_only_stages():
    """pipeline.stages.run is the one way to run a stage in a process: it knows every stage module, in
    dvc.yaml's order, and names the stages when asked for another; the runner imports the library only."""
    dvc_order = [stage_module(s).rsplit(".", 1)[1] for s in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"].values()]
    assert list(stages.NAMES) == list(dict.fromkeys(dvc_order))
    assert {f"pipeline.stages.{n}" for n in stages.NAMES} == set(STAGE_MODULES)
    assert {m for m in imports("pipeline.stages") if m != "pipeline"} <= {m for m in LIB}
    with pytest.raises(ValueError, match="no stage 'serve'; the stages: ingest, frame"):
        stages.run("serve")


def test_a_stage_runs_on_the_project_its_root_names(trained_project, tmp_path, monkeypatch):
    """stages.run(name, argv, root) reads and writes the project at `root` whatever the working directory
    (nothing lands there): frame, theory and split re-run on a copy of a trained project's ingest table
    give the bytes dvc repro gave."""
    root, cwd = tmp_path / "project", tmp_path / "elsewhere"
    cwd.mkdir()
    for f in [PARAMS_FILE, INGEST_TABLE]:
        (root / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(trained_project / f, root / f)
    monkeypatch.chdir(cwd)
    for name in ("frame", "theory", "split"):
        stages.run(name, (), root)
    for f in (FRAME_JSON, POINTS_TABLE, THEORY_JSON, SPLIT_TABLE, SPLIT_JSON):
        assert (root / f).read_bytes() == (trained_project / f).read_bytes(), f
    assert not any(cwd.iterdir())


def project_paths(module) -> set[str]:
    """Names of `module`'s relative Path constants: the artifact paths it imports and those it builds."""
    return {n for n, v in vars(module).items() if n.isupper() and isinstance(v, Path) and not v.is_absolute()}


def unrooted(mod: str) -> list[str]:
    """Where `mod` hands a project path to anything but str(), rooted() or link(), or asks it anything
    (`X.exists()`): an access relative to the working directory, not to the root (logging calls aside)."""
    names, out = project_paths(importlib.import_module(mod)), []
    for node in ast.walk(ast.parse(module_path(mod).read_text())):
        if isinstance(node, ast.Call):
            fn = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
            if fn in {"str", "rooted", "link", "debug", "info", "warning", "error"}:
                continue
            out += [f"line {node.lineno}: {fn}({a.id})" for a in [*node.args, *(k.value for k in node.keywords)]
                    if isinstance(a, ast.Name) and a.id in names]
        elif (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in names
              and node.attr not in {"name", "stem", "suffix", "parent"}):
            out.append(f"line {node.lineno}: {node.value.id}.{node.attr}")
    return out


ON_A_PROJECT = [f"pipeline.commands.{c}" for c in ("program", "path", "plan", "serve")]   # --project DIR


@pytest.mark.parametrize("mod", sorted(STAGE_MODULES) + ON_A_PROJECT)
def test_stages_and_robot_commands_open_project_files_under_its_root(mod):
    """A stage (and a command given --project) reads and writes `root / <artifact path>`: export wrote
    model.onnx into the working directory and read it back from the root (a stage run elsewhere checked
    another file, or none). The other commands work on the project in the working directory
    (docs/decisions.md)."""
    assert not unrooted(mod), f"{mod} opens project files in the working directory: {unrooted(mod)}"


def test_opt_in_dvc_files_run_only_commands():
    """ablation/dvc.yaml and fleet/dvc.yaml run a command (dvc repro of ./dvc.yaml never does)."""
    for f in ["ablation/dvc.yaml", "fleet/dvc.yaml"]:
        mods = {stage_module(s) for s in yaml.safe_load((ROOT / f).read_text())["stages"].values()}
        assert mods and mods <= CMDS, f"{f} runs {sorted(mods - CMDS)}, not a command"


@pytest.mark.parametrize("lib", LIB)
def test_library_imports_only_the_library(lib):
    outside = {m for m in imports(lib) if not m.startswith("pipeline.lib")}
    assert not outside, f"{lib} imports {outside}: the library must not import a stage or command"


@pytest.mark.parametrize("top,mod", MODULES, ids=[m for _, m in MODULES])
def test_stages_and_commands_import_only_the_library_and_their_own_modules(top, mod):
    """A stage imports only pipeline.lib; a command also its own package's modules (bench's each other)
    and the stage runner (the package pipeline.stages, never a stage module): no stage or command
    imports another."""
    own = (lambda m: m == top or m.startswith(top + ".") or m == "pipeline.stages") if top in CMDS else \
        (lambda m: False)
    outside = {m for m in imports(mod) if not (m.startswith("pipeline.lib") or m == "pipeline" or own(m))}
    kind = "a command imports only pipeline.lib, its own package and the runner" if top in CMDS else \
        "a stage imports only pipeline.lib"
    assert not outside, f"{mod} imports {sorted(outside)}: {kind}"


def scripts() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


@pytest.mark.parametrize("script", sorted(scripts()))
def test_every_script_is_a_command_main(script):
    """[project.scripts] spi-boter-<command> = the module `python -m pipeline.commands.<command>` runs, :main, a
    callable taking argv=None (the module calls it under __name__ == "__main__")."""
    target = scripts()[script]
    mod, _, attr = target.partition(":")
    command = script.removeprefix("spi-boter-")
    runs = f"pipeline.commands.{command}" + (".__main__" if (PKG / "commands" / command).is_dir() else "")
    assert command in COMMANDS and mod == runs and attr == "main", f"{script} = {target!r}: want {runs}:main"
    fn = getattr(importlib.import_module(mod), attr)
    argv = inspect.signature(fn).parameters.get("argv")
    assert callable(fn) and argv is not None and argv.default is None, f"{target}: not main(argv=None)"
    guard = [n for n in ast.parse(module_path(mod).read_text()).body if isinstance(n, ast.If)
             and ast.unparse(n.test) in ("__name__ == '__main__'", "'__main__' == __name__")]
    assert guard and "main()" in ast.unparse(guard[-1]), f"python -m {runs.removesuffix('.__main__')} does not call main()"


def test_every_command_has_a_script():
    assert {s.removeprefix("spi-boter-") for s in scripts()} == set(COMMANDS)


def test_pyproject_packages_are_every_package():
    """A non-editable install ships every package under pipeline/ (pipeline.commands.bench included)."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in PKG.rglob("__init__.py")}
    assert listed == found


@pytest.mark.parametrize("name", sorted(STAGES))
def test_stage_deps_are_exactly_the_code_it_runs(name):
    """deps' .py files == the stage module + the project modules it imports (transitively)."""
    stage = dvc_stages()[name]
    code = {str(module_path(m).relative_to(ROOT)) for m in closure(STAGES[name])}
    deps = {d for d in stage.get("do", stage)["deps"] if d.endswith(".py")}
    assert not code - deps, f"stage {name}: code it runs but does not depend on: {sorted(code - deps)}"
    assert not deps - code, f"stage {name}: depends on code it does not run: {sorted(deps - code)}"


def declared_params(stage: dict) -> set[str]:
    """The sections the stage's module says it reads (its PARAMS; a dict per subcommand, e.g. validate's)."""
    cmd = stage.get("do", stage)["cmd"].split()
    declared = importlib.import_module(cmd[2]).PARAMS
    return set(declared[cmd[3]] if isinstance(declared, dict) else declared)


@pytest.mark.parametrize("name", sorted(STAGES))
def test_stage_params_are_exactly_the_sections_it_reads(name):
    """dvc.yaml `params:` (by section: `validate.register_points` is the validate section) == the
    module's PARAMS, which config.for_stage hands the stage and nothing else: a setting the stage
    reads re-runs it, and no other setting does."""
    stage = dvc_stages()[name]
    listed = {p.split(".")[0] for p in stage.get("do", stage).get("params", [])}
    declared = declared_params(stage)
    assert declared == listed, (f"stage {name}: reads {sorted(declared)} but dvc.yaml lists {sorted(listed)}")


def section_keys_read(source: str, section: str) -> set[str]:
    """Keys the module reads of params section `section` by name: `x["section"]["key"]` or `.get("key")`, or the
    same on a name bound to `x["section"]` in that function (plain, annotated or tuple assignment, walrus)."""
    def is_section(node):
        return isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and node.slice.value == section

    def bindings(scope):
        for node in ast.walk(scope):
            if isinstance(node, ast.Assign):
                for t in node.targets:
                    if isinstance(t, ast.Tuple) and isinstance(node.value, ast.Tuple):
                        yield from zip(t.elts, node.value.elts)
                    else:
                        yield t, node.value
            elif isinstance(node, (ast.AnnAssign, ast.NamedExpr)) and node.value is not None:
                yield node.target, node.value

    def reads(scope, bound):
        on = lambda v: is_section(v) or isinstance(v, ast.Name) and v.id in bound        # noqa: E731
        for node in ast.walk(scope):
            if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and on(node.value):
                yield node.slice.value
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get"
                  and node.args and isinstance(node.args[0], ast.Constant) and on(node.func.value)):
                yield node.args[0].value

    tree = ast.parse(source)
    scopes = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    module = ast.Module(body=[n for n in tree.body if not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                                         ast.ClassDef))], type_ignores=[])
    out = set()
    for scope in scopes + [module]:
        bound = {t.id for t, v in bindings(scope) if isinstance(t, ast.Name) and is_section(v)}
        out |= set(reads(scope, bound))
    return out


@pytest.mark.parametrize("name", sorted(STAGES))
def test_a_key_the_stage_reads_of_a_section_it_lists_by_key_is_listed(name):
    """Where dvc.yaml lists a section by its keys (`validate.register_points`), every key of that section the
    stage module reads by name is among them: else a change of it leaves the stage's outputs stale
    (validate.tool_significance was read and not listed). The module only: the library takes explicit values."""
    stage = dvc_stages()[name]
    listed = stage.get("do", stage).get("params", [])
    source = module_path(STAGES[name]).read_text()
    for section in {p.split(".")[0] for p in listed if "." in p} - set(listed):
        for key in section_keys_read(source, section):
            covered = any(p == f"{section}.{key}" or p.startswith(f"{section}.{key}.") for p in listed)
            assert covered, f"stage {name} reads {section}.{key}, which dvc.yaml's params do not list"


def test_a_stage_sees_only_its_declared_sections():
    from pipeline.stages import split
    params = load_params(ROOT / "params.yaml")
    with pytest.raises(KeyError):
        for_stage(params, split.PARAMS)["model"]
    assert set(for_stage(params, split.PARAMS)) == {"split"}


def test_closure_sees_function_local_and_transitive_imports(tmp_path):
    """The walk behind the deps test: train reaches robots.py only through the library."""
    c = closure("pipeline.stages.train")
    assert {"pipeline.lib.robot.robots", "pipeline.lib.robot.kinematics", "pipeline.lib.learning.model",
            "pipeline.lib.project.config", "pipeline"} <= c
    assert "pipeline.lib.reading.readers" not in c and "pipeline.stages.ingest" not in c


def git_dvc_repo(tmp: Path) -> dict:
    """A copy of the project (code, dvc.yaml, params, raw data) in a fresh git + DVC repo whose
    dvc.lock records every stage as run (outputs are placeholders: nothing is computed)."""
    for p in ["pipeline", "data/raw", "dvc.yaml", "params.yaml", "reports/validation/.gitkeep",
              "reports/campaigns/.gitkeep", "data/interim/campaigns/.gitkeep"]:
        src, dst = ROOT / p, tmp / p
        if src.is_dir():
            shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, dst)
    env = {**os.environ, "DVC_NO_ANALYTICS": "1", "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t",
           "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    run = lambda *cmd: subprocess.run(cmd, cwd=tmp, env=env, check=True, capture_output=True, text=True)
    run("git", "init", "-q")
    run("dvc", "init", "-q")
    params = yaml.safe_load((tmp / "params.yaml").read_text())
    for stage in dvc_stages().values():
        if "matrix" in stage:
            continue
        for key in foreach_keys(stage, params):
            body = stage.get("do", stage)
            for out in body.get("outs", []) + body.get("metrics", []) + body.get("plots", []):
                name = (out if isinstance(out, str) else next(iter(out))).replace("${key}", str(key))
                path = tmp / name
                if path.suffix:                                # a file
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_text("placeholder\n")
                else:                                          # a folder
                    path.mkdir(parents=True, exist_ok=True)
                    (path / "placeholder.tsv").write_text("step\n")
    run("dvc", "commit", "-f", "-q")
    return {"run": run}


@pytest.fixture(scope="module")
def placeholder_repo(tmp_path_factory):
    """git_dvc_repo, once for the edits below (each undone after its check): its folder and runner."""
    tmp = tmp_path_factory.mktemp("placeholders")
    return tmp, git_dvc_repo(tmp)


@pytest.mark.slow
@pytest.mark.parametrize("edited", ["pipeline/lib/robot/robots.py", "pipeline/lib/robot/kinematics.py",
                                    "pipeline/lib/learning/model.py"])
def test_editing_library_code_makes_dvc_status_report_its_stages(placeholder_repo, edited):
    tmp_path, repo = placeholder_repo
    assert "Data and pipelines are up to date" in repo["run"]("dvc", "status").stdout
    before = (tmp_path / edited).read_bytes()
    try:
        with open(tmp_path / edited, "a") as f:
            f.write("# an edit\n")
        status = json.loads(repo["run"]("dvc", "status", "--json").stdout)
    finally:
        (tmp_path / edited).write_bytes(before)            # the next edit starts from a current repo
    stale = {name for name, changes in status.items()
             if any(c.get("changed deps", {}).get(edited) == "modified" for c in changes if isinstance(c, dict))}
    users = {name for name, mod in STAGES.items() if not name.startswith("ablation/")
             and edited in {str(module_path(m).relative_to(ROOT)) for m in closure(mod)}}
    params = yaml.safe_load((tmp_path / "params.yaml").read_text())
    users = {u if k is None else f"{u}@{k}"                   # a foreach stage, once per item
             for u in users for k in foreach_keys(dvc_stages()[u], params)}
    assert stale == users and stale                    # every stage that runs it, and only those
    if edited.endswith("robots.py"):                   # the DH tables reach every stage but split
        assert stale == {"ingest", "frame", "theory", "calibrate", "parts", "train", "baselines", "evaluate",
                         "compensate", "validate@twin_side", "validation", "export", "report"}


STANDS_ALONE_EXCEPT = ("data/presets/", "pipeline/commands/bench/", "tests/test_ingest.py", "tests/test_preset.py",
                       "tests/test_layout.py", "README.md", "docs/data-format.md", "docs/experiments.md",
                       "CHANGELOG.md")


def test_the_project_stands_on_its_own():
    """Only the presets, the benchmarks, the tests on the public datasets (which skip without them) and
    the pages saying where to put those datasets name the folder beside the checkout; nothing cites a
    document outside the repository."""
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    named = [f for f in files if (ROOT / f).is_file() and f.endswith((".py", ".md", ".yaml", ".toml", ".txt", ".lock"))
             and not f.startswith(STANDS_ALONE_EXCEPT)
             and any(s in (ROOT / f).read_text(errors="ignore") for s in ("../shared", "DATA_FORMAT.md", "SPEC.md"))]
    assert not named, f"these refer to documents or data outside the repository: {named}"


def test_every_committed_campaign_file_is_checked_out_as_committed():
    """A review (2026-12-06): with git's core.autocrlf (Git for Windows' default) a clone converted data/raw's
    CSV and JSON files to CRLF: their SHA-256 (reports/ingest.json) no longer the twin's, so the compensate
    stage skipped its drive check ("not the twin's campaign") and `dvc status` called the clone stale. Every
    file under data/ is now binary to git's line-ending conversion (.gitattributes)."""
    files = subprocess.run(["git", "ls-files", "data"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    out = subprocess.run(["git", "check-attr", "text", "--", *files], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert files and len(out) == len(files)
    assert [line for line in out if not line.endswith(": text: unset")] == []
