"""Atomic writes leave files and directories with the permissions of any new file."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Written in a child process: the umask belongs to the process, and this one's stays as it is.
WRITE = """
import json, os, sys
from pathlib import Path
from quadformer.io import atomic_dir, atomic_path, atomic_write_text, write_json

os.umask(int(sys.argv[2], 8))
root = Path(sys.argv[1])
(root / "plain.txt").write_text("x")
(root / "plain_dir").mkdir()
atomic_write_text(root / "text.txt", "x")
write_json(root / "doc.json", {"a": 1})
with atomic_path(root / "by_name.bin") as tmp:
    tmp.write_bytes(b"x")
with atomic_dir(root / "dataset") as tmp:
    (tmp / "inside.json").write_text("{}")
with atomic_dir(root / "dataset", overwrite=True) as tmp:      # replacing an existing directory
    (tmp / "inside.json").write_text("{}")
print(json.dumps({p.name: p.stat().st_mode & 0o777 for p in root.iterdir()}))
"""


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077], ids=oct)
def test_atomic_writes_honour_the_umask(umask, tmp_path):
    out = subprocess.run([sys.executable, "-c", WRITE, str(tmp_path), oct(umask)],
                         capture_output=True, text=True, check=True).stdout
    modes = json.loads(out)
    assert set(modes) == {"plain.txt", "plain_dir", "text.txt", "doc.json", "by_name.bin", "dataset"}  # no leftovers
    file_mode, dir_mode = 0o666 & ~umask, 0o777 & ~umask
    assert modes["plain.txt"] == file_mode and modes["plain_dir"] == dir_mode
    for name in ("text.txt", "doc.json", "by_name.bin"):
        assert modes[name] == file_mode, (name, oct(modes[name]))
    assert modes["dataset"] == dir_mode, oct(modes["dataset"])
