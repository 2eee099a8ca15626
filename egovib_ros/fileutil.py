"""Output files that appear only when complete (CONTRACT section 3: no partial output)."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, *, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling path; move it onto `path` only if the block succeeds.

    For `directory=True` (rosbag2 bags) the yielded path does not exist yet, so
    writers that insist on creating the directory themselves can do so.
    """
    final = Path(path)
    parent = final.parent if str(final.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp_root = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=parent))
    tmp = tmp_root / final.name
    try:
        yield tmp
        if final.exists():
            if final.is_dir() and not final.is_symlink():
                shutil.rmtree(final)
            else:
                final.unlink()
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
