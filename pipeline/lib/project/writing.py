"""Files written whole or not at all, never over an input (docs/robot-cell.md, "Safe by construction").

    write_together({path: text or bytes, ...}, inputs=[...])   every file, or none of them
    write_file(path, text or bytes)                             one file, whole or not at all
    write_by(path, save)                                        a file save(path) writes itself (torch.save,
                                                                onnx.save_model), whole or not at all
    csv_text(df, float_format)                                  df.to_csv(index=False, ...)'s text, fast

Each file goes to a temporary file beside it first; only when every one is written are they renamed
into place, and should a rename fail, those before it are undone (the files they replaced put back). An
output that is an input by any spelling (a hard link, a symbolic link, `..`), or a folder, is refused
before anything is written, as are two outputs that are one file and (`owned`) one over the project's own
files.
"""
import os
import shutil
import tempfile
from pathlib import Path

import pandas as pd


def same_file(a, b) -> bool:
    """a and b name one file: the same inode (hard and symbolic links), or the same resolved path."""
    a, b = Path(a), Path(b)
    try:
        return os.path.samefile(a, b)
    except OSError:                                   # one does not exist (yet)
        return a.resolve() == b.resolve()


def check_outputs(outputs, inputs=(), owned=()) -> None:
    """A ValueError when an output is an input, two outputs are one file, an output's folder is a file, or an
    output is (or lies in a folder that is) one of the project's own files, `owned` (artifacts.project_owned):
    written over, `dvc repro` and `git status` would not say why."""
    outputs, inputs = [Path(p) for p in outputs], [Path(p) for p in inputs]
    for o in outputs:
        folder = next((f for f in o.parents if f.exists()), None)   # the nearest that exists
        if folder is not None and not folder.is_dir():
            raise ValueError(f"{folder} is a file, not a folder: cannot write {o} there")
    for o in outputs:
        for i in inputs:
            if same_file(o, i):
                raise ValueError(f"{o} is the input {i} (the same file): choose another output path")
    for o in outputs:
        for w in owned:
            if same_file(o, w) or Path(w).resolve() in o.resolve().parents:
                raise ValueError(f"{o} is the project's own {w} (a pipeline output, a setting, a committed "
                                 "campaign or benchmark record): choose another output path")
    for k, a in enumerate(outputs):
        for b in outputs[k + 1:]:
            if same_file(a, b):
                raise ValueError(f"{a} and {b} are the same file: choose two output paths")


def left_as_they_were(outputs) -> str:
    """For a refusal that writes nothing: which of the outputs exist already (an earlier run's, which a user
    could take for this one's), as the end of its message; "" when none does."""
    old = [str(p) for p in outputs if Path(p).exists()]
    return f"; {', '.join(old)}: an earlier run's, left as they were, not this one's" if old else ""


def write_together(files: dict, inputs=()) -> None:
    """Write every {path: str | bytes} or none (an OSError naming the path that failed)."""
    check_outputs(files, inputs)
    for path in files:
        if Path(path).is_dir():
            raise OSError(f"cannot write {path} (a folder); nothing written")
    temps = {}
    try:
        for path, data in files.items():
            path = Path(path)
            try:
                fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            except OSError as e:
                raise OSError(f"cannot write {path} ({e.strerror}); nothing written") from None
            temps[path] = tmp
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(data.encode() if isinstance(data, str) else data)
                    f.flush()
                    os.fsync(f.fileno())
                os.chmod(tmp, 0o644)
            except OSError as e:                          # a disk full: which file, not only the errno
                raise OSError(f"cannot write {path} ({e.strerror or e}); nothing written") from None
        replace_all(temps)
        temps = {}
    finally:
        for tmp in temps.values():
            Path(tmp).unlink(missing_ok=True)


def write_file(path, data) -> None:
    """One {path: str | bytes}, whole or not at all (write_together), its folder made."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_together({Path(path): data})


def write_by(path, save) -> None:
    """save(p) writes a file at p, whole or not at all at path: p has path's name in a new folder beside it
    (torch.save names its archive's folder after the file: the same bytes), renamed into place once written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    folder = tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        tmp = Path(folder) / path.name
        save(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def replace_all(temps: dict) -> None:
    """Rename each {path: its written temporary file} into place; if one fails, put back the files the renames
    before it replaced (kept beside them until then) and raise an OSError naming the path."""
    done = []                                         # (path, a copy of the file it replaced, or None)
    try:
        for path, tmp in temps.items():
            old = f"{tmp}.old" if path.exists() else None
            if old:
                keep(path, old)
            try:
                os.replace(tmp, path)
            except OSError as e:
                if old:
                    Path(old).unlink()
                raise OSError(f"cannot write {path} ({e.strerror}); nothing written") from None
            done.append((path, old))
    except OSError:
        for path, old in reversed(done):
            if old is None:
                path.unlink(missing_ok=True)
            else:
                os.replace(old, path)
        raise
    for _, old in done:
        if old:
            Path(old).unlink(missing_ok=True)


def keep(path: Path, copy: str) -> None:
    """copy: the file at path, as a hard link (or a copy where the file system has none)."""
    try:
        os.link(path, copy)
    except OSError:
        shutil.copy2(path, copy)


def csv_text(df: pd.DataFrame, float_format: str = "%.6f") -> str:
    """`df.to_csv(index=False, float_format=float_format, lineterminator="\\n")`, byte for byte, one
    `%` per row instead of one per cell (a 200k-row Δθ table: seconds, not tens of seconds). Frames the
    fast path cannot vouch for (a NaN, a text cell the csv module would quote, other dtypes) go to pandas."""
    def plain(values) -> bool:                       # text the csv module writes as it is
        return all(type(v) is str and v and not any(x in v for x in ',"\r\n') for v in values)

    def text(c) -> bool:
        return c.dtype == object or pd.api.types.is_string_dtype(c.dtype)

    kinds = [float_format if c.dtype.kind == "f" and not c.isna().any() else
             "%s" if c.dtype.kind in "iub" or (text(c) and plain(c)) else None for _, c in df.items()]
    if None in kinds or not plain(map(str, df.columns)):
        return df.to_csv(index=False, float_format=float_format, lineterminator="\n")
    row = ",".join(kinds) + "\n"
    cols = [c.tolist() for _, c in df.items()]
    return ",".join(map(str, df.columns)) + "\n" + "".join(row % r for r in zip(*cols))


def remove_stale(folder: Path, names, suffixes: tuple) -> list:
    """Delete folder's files with one of suffixes whose stem is not in names (the outputs of a campaign no
    longer in params.yaml: a folder a stage depends on whole would hash them, and dvc.lock would change);
    the paths removed."""
    names = set(names)
    gone = sorted(f for f in Path(folder).glob("*") if f.suffix in suffixes and f.stem not in names)
    for f in gone:
        f.unlink()
    return gone
