"""constraints.txt (issue 21): the exact versions the committed dvc.lock was made with, so that a
fresh clone's install gives the same output bytes. Every dependency pyproject.toml names is pinned
there, within pyproject's own range, and .ci/install installs with it."""
import re
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

tomllib = pytest.importorskip("tomllib")                  # Python 3.11+

ROOT = Path(__file__).resolve().parents[1]


def pins() -> dict:
    """{canonical name: Version} of constraints.txt; every line a `name==version`."""
    out = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            m = re.fullmatch(r"([A-Za-z0-9._-]+)==([^\s=]+)", line)
            assert m, f"constraints.txt: {line!r} is not an exact pin"
            name = canonicalize_name(m[1])
            assert name not in out, f"constraints.txt pins {m[1]} twice"
            out[name] = Version(m[2])
    return out


def test_every_dependency_is_pinned_within_pyproject_range():
    pinned = pins()
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    for dep in map(Requirement, deps):
        name = canonicalize_name(dep.name)
        assert name in pinned, f"{dep.name} is not pinned in constraints.txt"
        assert dep.specifier.contains(pinned[name], prereleases=True), \
            f"constraints.txt pins {dep.name}=={pinned[name]}, outside pyproject's {dep}"
    for numeric in ("numpy", "scipy", "pandas", "pyarrow", "onnx", "onnxscript", "onnxruntime"):
        assert numeric in pinned


def test_ci_install_uses_the_constraints():
    install = (ROOT / ".ci/install").read_text()
    assert re.search(r"pip install .*-c constraints\.txt", install)
