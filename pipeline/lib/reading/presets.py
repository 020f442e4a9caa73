"""Presets: partial params for a known dataset, deep-merged over params.yaml.

    python -m pipeline.commands.preset gtpn-ur5 [--params params.yaml]   # rewrite params.yaml, print changes
    merged_params("ipa-ur10", base)  -> dict                     # in-process, writes nothing

A preset is data/presets/NAME.yaml (or any YAML path), optionally `extends:`
another preset. Mappings merge key by key (a `campaigns` or `target` mapping is
replaced whole); anything else (scalars, lists) replaces the base value. Paths
inside a preset are relative to the project root, like the rest of params.yaml.
params.yaml is rewritten with ruamel.yaml's round trip when it is installed
(DVC depends on it), so comments and layout survive; otherwise with PyYAML
(comments lost). The result is re-read and checked against the merge.
"""
import copy
import io
from pathlib import Path

from pipeline.lib.project.config import yaml_text, yaml_values
from pipeline.lib.project.writing import write_file

PRESETS = Path(__file__).resolve().parents[3] / "data" / "presets"


def preset_path(name_or_path) -> Path:
    """A preset name (data/presets/NAME.yaml) or a path to a YAML file."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    path = PRESETS / f"{name_or_path}.yaml"
    if not path.exists():
        known = sorted(q.stem for q in PRESETS.glob("*.yaml"))
        raise ValueError(f"unknown preset {name_or_path!r}; known: {', '.join(known) or 'none'}")
    return path


def load_preset(name_or_path) -> dict:
    """The preset's settings; `extends: OTHER` merges them over preset OTHER's."""
    path = preset_path(name_or_path)
    preset = yaml_values(path.read_text(), str(path)) or {}
    base = preset.pop("extends", None)
    return preset if base is None else deep_merge(load_preset(base), preset)


REMOVED = "(removed)"                  # changes(): the new value of a key the merge no longer holds
REPLACED = {"campaigns", "target", "tcp"}   # mappings replaced whole: a preset's own (validation or training)
                                    # campaigns; a rigid target's geometry (ingest.target: a campaign's own);
                                    # its robot's tool centre points (robot.tcp)


def deep_merge(base: dict, over: dict) -> dict:
    """A new dict: `over` on top of `base`, mappings merged recursively (but REPLACED keys)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and k not in REPLACED:
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def merged_params(name_or_path, base: dict) -> dict:
    """`base` (a params dict) with the preset merged over it."""
    return deep_merge(base, load_preset(name_or_path))


def changes(old: dict, new: dict, prefix: str = "") -> list:
    """[(dotted key, old value, new value)] for every leaf that differs, and (new value REMOVED) every key of
    old that new no longer holds (a REPLACED mapping's)."""
    out = [(f"{prefix}{k}", v, REMOVED) for k, v in old.items() if k not in new] if isinstance(old, dict) else []
    for k in new:
        key = f"{prefix}{k}"
        a, b = old.get(k) if isinstance(old, dict) else None, new[k]
        if isinstance(a, dict) and isinstance(b, dict):
            out += changes(a, b, key + ".")
        elif a != b or (isinstance(old, dict) and k not in old):
            out.append((key, a, b))
    return out


def _roundtrip_merge(node, over: dict) -> None:
    """Merge `over` into a ruamel CommentedMap in place (new lists in flow style; a list the
    file already holds is refilled in place, keeping its style and the comments around it)."""
    from ruamel.yaml.comments import CommentedMap, CommentedSeq
    from ruamel.yaml.scalarstring import DoubleQuotedScalarString
    for k, v in over.items():
        if node.get(k) == v:
            continue                                    # unchanged: leave the text as it is
        if isinstance(v, dict) and isinstance(node.get(k), CommentedMap) and k not in REPLACED:
            _roundtrip_merge(node[k], v)
        elif isinstance(v, list) and isinstance(node.get(k), CommentedSeq) and not node[k].fa.flow_style():
            node[k][:] = v                              # a block list (as `dvc exp run -S` writes them)
        elif isinstance(v, list):
            seq = CommentedSeq(v)
            seq.fa.set_flow_style()
            node[k] = seq
        elif isinstance(v, str) and len(v) <= 2 and not v.isalnum():
            node[k] = DoubleQuotedScalarString(v)       # ";", ",", "\t" as the file writes them
        else:
            node[k] = v


def render(text: str, preset: dict) -> str:
    """params.yaml text with the preset merged in, its comments kept (ruamel.yaml's round trip) where that
    reads back as the merged values (config.yaml_values, as DVC reads them), else plain (config.yaml_text)."""
    merged = deep_merge(yaml_values(text, "params.yaml") or {}, preset)
    try:
        from ruamel.yaml import YAML
        from ruamel.yaml.error import YAMLError
        rt = YAML()
        rt.preserve_quotes = True
        rt.width = 4096
        rt.representer.add_representer(
            type(None), lambda r, _: r.represent_scalar("tag:yaml.org,2002:null", "null"))
        doc = rt.load(text)
        _roundtrip_merge(doc, preset)
        buf = io.StringIO()
        rt.dump(doc, buf)
        out = buf.getvalue()
        if yaml_values(out, "params.yaml") == merged:
            return out
    except YAMLError:
        pass                                            # it lost the layout: plain YAML
    return yaml_text(merged)


def apply_preset(name_or_path, params_path="params.yaml") -> list:
    """Merge the preset into the params file (rewritten in place); returns the changes."""
    path = Path(params_path)
    text = path.read_text()
    preset = load_preset(name_or_path)
    diff = changes(yaml_values(text, str(path)) or {}, deep_merge(yaml_values(text, str(path)) or {}, preset))
    if diff:
        write_file(path, render(text, preset))
    return diff
