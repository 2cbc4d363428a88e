"""The quick starts run as written: every ```python block of README.md and of
docs/pages/getting-started.md, on built-in synthetic data only.

One fresh Python process per file runs that file's blocks in order in one namespace, in an empty
working folder, with jaxloc's compilation cache in a temporary folder of its own
(``JAXLOC_CACHE_DIR``; shared by the two files, so the second file's quick starts load what the
first compiled, as a user's second script would). Nothing is skipped: a block that cannot run
(one that reads a user's own files) belongs on another page.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FILES = ("README.md", "docs/pages/getting-started.md")
BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


def python_blocks(path: Path) -> list[str]:
    return BLOCK.findall(path.read_text(encoding="utf-8"))


def program(path: Path) -> str:
    """The file's blocks as one script; a failure names the block (1-based) it happened in."""
    parts = ["import sys", "namespace = {'__name__': '__main__'}"]
    for index, block in enumerate(python_blocks(path), 1):
        parts.append(f"sys.stderr.write('--- block {index}\\n')")
        parts.append(f"exec(compile({block!r}, '{path.name} block {index}', 'exec'), namespace)")
    return "\n".join(parts) + "\n"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("jaxloc_cache")


def test_both_files_have_the_two_quick_starts():
    for name in FILES:
        text = "\n".join(python_blocks(REPO / name))
        assert "from jaxloc.sg2loc import" in text and "localize(" in text, name
        assert "m2loc.localize_scan(" in text, name
        assert "jaxloc.enable_compilation_cache()" in text, name


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", FILES)
def test_the_python_blocks_run(name, cache, tmp_path):
    env = {
        key: value
        for key, value in os.environ.items()
        if not key.startswith(("JAXLOC_", "JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))
    }
    env.update(
        JAXLOC_CACHE_DIR=str(cache),
        JAX_PLATFORMS="cpu",
        MPLBACKEND="Agg",
        PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")])),
    )
    done = subprocess.run(
        [sys.executable, "-c", program(REPO / name)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=280,
    )
    assert done.returncode == 0, f"{name}:\n{done.stdout[-3000:]}\n{done.stderr[-6000:]}"
