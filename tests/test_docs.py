"""Every fenced block of docs/plugins.md is real: files are written, commands run in order in a fresh folder (with
entry points enabled), and a ``text`` block after a command lists lines its output must contain.

A block's first line ``# <path>`` makes it a file (the second line after a Hydra config's ``# @package`` line); other
``python`` and ``bash`` blocks are commands. A block may be
left out only with ``<!-- docs-test: skip (reason) -->`` on the line before it, which must stay rare.
"""

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from gpnerf_core.testing import CHECKS

DOC = Path(__file__).resolve().parents[1] / "docs" / "plugins.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```$", re.M | re.S)
SKIP = re.compile(r"<!-- docs-test: skip \((.+)\) -->\s*\Z")
FILE_HEADER = re.compile(r"#\s*([\w./-]+\.(?:py|toml|yaml|txt))\s*$")
MAX_SKIPS = 1


@dataclass
class Block:
    language: str
    text: str
    line: int
    skip: str | None
    file: str | None


def blocks(path: Path = DOC) -> list[Block]:
    source = path.read_text()
    found = []
    for match in FENCE.finditer(source):
        before = source[: match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        skip = SKIP.search(before)
        first, second = (match.group(2).split("\n") + [""])[:2]
        # A Hydra config's ``# @package`` line must come first; its path then heads the second line.
        header = FILE_HEADER.match(second if first.startswith("# @package") else first)
        found.append(Block(match.group(1), match.group(2), source.count("\n", 0, match.start()) + 1,
                           skip.group(1) if skip else None, header.group(1) if header else None))
    return found


def words(text: str) -> str:
    return " ".join(text.split())


def env_for(cache: Path) -> dict[str, str]:
    """The test environment with entry points enabled, the venv first on PATH, and no network for pip."""
    env = {k: v for k, v in os.environ.items() if k not in ("GPNERF_DISABLE_PLUGIN_AUTOLOAD", "GPNERF_DISABLE_PLUGINS")}
    path = os.pathsep.join([os.path.dirname(sys.executable), env.get("PATH", "")])
    return dict(env, PATH=path, GPNERF_CACHE=str(cache), OMP_NUM_THREADS="1", PIP_NO_INDEX="1",
                PIP_DISABLE_PIP_VERSION_CHECK="1")


def run_block(block: Block, cwd: Path, env: dict[str, str]) -> str:
    command = [sys.executable, "-"] if block.language == "python" else ["bash", "-euo", "pipefail", "-s"]
    result = subprocess.run(command, input=block.text, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"{DOC.name} line {block.line} ({block.language}) exited {result.returncode}:\n" \
                                   f"{output[-3000:]}"
    return output


def test_every_block_is_a_file_a_command_or_expected_output():
    found = blocks()
    for block in found:
        assert block.language in ("python", "bash", "toml", "yaml", "text"), f"line {block.line}: ```{block.language}"
        if block.language in ("toml", "yaml"):
            assert block.file, f"line {block.line}: a {block.language} block must start with '# <path>'"
    skips = [block for block in found if block.skip]
    assert len(skips) <= MAX_SKIPS, f"{len(skips)} blocks are skipped: {[(b.line, b.skip) for b in skips]}"


def test_the_docs_plugin_goes_through_the_contract_kit():
    found = blocks()
    plugins = [Path(b.file).stem for b in found  # a plugin that registers components (not presets only)
               if b.file and b.file.endswith(".py") and "@hookimpl" in b.text and "def gpnerf_register_" in b.text]
    assert plugins, "docs/plugins.md shows no complete plugin module"
    commands = [b.text for b in found if not b.file and not b.skip and b.language == "python"]
    for name in plugins:
        assert any(f'check_plugin("{name}"' in text for text in commands), f"no block runs the kit on {name}"


def test_the_checks_table_lists_every_check_of_every_kind():
    rows = dict(re.findall(r"^\| `(\w+)` \| ([a-z_, ]+) \|$", DOC.read_text(), re.M))
    assert rows == {kind: ", ".join(checks) for kind, checks in CHECKS.items()}


def test_every_command_in_the_docs_runs(tmp_path):
    workdir, env = tmp_path / "work", env_for(tmp_path / "cache")
    workdir.mkdir()
    found = blocks()
    distributions = []
    try:
        output = None
        for block in found:
            if block.skip:
                output = None
            elif block.file:
                target = workdir / block.file
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_text(block.text)
                if target.name == "pyproject.toml":
                    distributions.append(re.search(r'^name = "(.+)"$', block.text, re.M).group(1))
                output = None
            elif block.language in ("python", "bash"):
                output = run_block(block, workdir, env)
            elif block.language == "text" and output is not None:
                for line in filter(None, map(words, block.text.splitlines())):
                    assert line in words(output), f"line {block.line}: {line!r} not in the output:\n{output[-3000:]}"
    finally:
        for name in distributions:
            subprocess.run([sys.executable, "-m", "pip", "uninstall", "-y", "-q", name], env=env, capture_output=True)
    for name in distributions:
        shown = subprocess.run([sys.executable, "-m", "pip", "show", name], env=env, capture_output=True)
        assert shown.returncode == 1, f"{name} is still installed"
