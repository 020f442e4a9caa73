"""Files written whole or not at all, never over an input (docs/robot-cell.md, "Safe by construction").

    write_together({path: text or bytes, ...}, inputs=[...])   every file, or none of them

Each file goes to a temporary file beside it first; only when every one is written are they renamed
into place. An output that is an input by any spelling (a hard link, a symbolic link, `..`) is refused
before anything is written, as are two outputs that are one file.
"""
import os
import tempfile
from pathlib import Path


def same_file(a, b) -> bool:
    """a and b name one file: the same inode (hard and symbolic links), or the same resolved path."""
    a, b = Path(a), Path(b)
    try:
        return os.path.samefile(a, b)
    except OSError:                                   # one does not exist (yet)
        return a.resolve() == b.resolve()


def check_outputs(outputs, inputs=()) -> None:
    """A ValueError when an output is an input, or two outputs are one file."""
    outputs, inputs = [Path(p) for p in outputs], [Path(p) for p in inputs]
    for o in outputs:
        for i in inputs:
            if same_file(o, i):
                raise ValueError(f"{o} is the input {i} (the same file): choose another output path")
    for k, a in enumerate(outputs):
        for b in outputs[k + 1:]:
            if same_file(a, b):
                raise ValueError(f"{a} and {b} are the same file: choose two output paths")


def write_together(files: dict, inputs=()) -> None:
    """Write every {path: str | bytes} or none (an OSError naming the path that failed)."""
    check_outputs(files, inputs)
    temps = {}
    try:
        for path, data in files.items():
            path = Path(path)
            try:
                fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
            except OSError as e:
                raise OSError(f"cannot write {path} ({e.strerror}); nothing written") from None
            temps[path] = tmp
            with os.fdopen(fd, "wb") as f:
                f.write(data.encode() if isinstance(data, str) else data)
                f.flush()
                os.fsync(f.fileno())
            os.chmod(tmp, 0o644)
        for path, tmp in temps.items():
            os.replace(tmp, path)
        temps = {}
    finally:
        for tmp in temps.values():
            Path(tmp).unlink(missing_ok=True)
