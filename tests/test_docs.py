"""The documentation: the site builds in strict mode, the generated tables are current, every public function
of the API pages has a docstring, and every command and Python block of README.md and docs/usage.md runs,
printing what the page shows.

A block may carry a directive, an HTML comment on the line before its fence:

Every block runs where the reader stands: the root of a clone. Each gets a fresh stand-in for it (the root's
files linked, ``examples/`` copied), so what a command writes lands there and not in the repository.

* ``<!-- test: args ... -->``: append these arguments to each command of the block (to keep a long job short:
  fewer steps, fewer pairs);
* ``<!-- test: needs modelnet40 -->``, ``needs dragon`` or ``needs 3dmatch``: the data the block reads, through
  ``$MODELNET40``, ``$SCANS`` or ``$THREEDMATCH`` (skipped, with the reason, where ``../shared`` lacks it);
* ``<!-- test: ci -->``: the README's test command, which ``.ci/run`` must run as written.

A fenced ``text`` block right after a block is the output it prints: compared line by line, numbers within
float rounding of another machine (1e-3 relative, 1e-5 absolute) and timings ("1.23 s") not at all.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest
from conftest import DRAGON_DIR, MODELNET_DIR, SHARED

THREEDMATCH_DIR = SHARED / "data" / "3dmatch"

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = ("README.md", "docs/usage.md")


@dataclasses.dataclass
class Block:
    page: str
    line: int
    language: str
    code: str
    directives: dict
    output: str | None

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"


def read_blocks(page: str) -> list[Block]:
    lines = (ROOT / page).read_text().split("\n")
    blocks, i, after_code = [], 0, None
    while i < len(lines):
        fence = re.match(r"^```(\w+)\s*$", lines[i])
        if not fence:
            if lines[i].strip():  # prose between a block and a text block: that text is not the block's output
                after_code = None
            i += 1
            continue
        start, language = i, fence.group(1)
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        code = "\n".join(lines[start + 1 : end])
        i = end + 1
        if language == "text":
            if after_code is not None:  # the output of the block just before (blank lines between at most)
                after_code.output = code
            after_code = None
            continue
        directives = {}
        comment = re.match(r"^<!-- test: (.*) -->$", lines[start - 1]) if start else None
        if comment:
            for part in comment.group(1).split(";"):
                key, _, value = part.strip().partition(" ")
                directives[key] = value.strip()
        after_code = None
        if language in ("python", "bash"):
            blocks.append(Block(page, start + 1, language, code, directives, None))
            after_code = blocks[-1]
    return blocks


BLOCKS = [b for page in PAGES for b in read_blocks(page)]
TIMING = re.compile(r"\d+(\.\d+)? s\b")
NUMBER = re.compile(r"-?\d+\.?\d*(?:e[-+]?\d+)?")


def same_output(shown: str, printed: str) -> tuple[bool, str]:
    """Whether the printed output is the one the page shows, up to float rounding and timings."""
    shown_lines = [TIMING.sub("T s", line).rstrip() for line in shown.strip("\n").split("\n")]
    printed_lines = [TIMING.sub("T s", line).rstrip() for line in printed.strip("\n").split("\n")]
    if len(shown_lines) != len(printed_lines):
        return False, f"{len(printed_lines)} lines printed, {len(shown_lines)} shown"
    for a, b in zip(shown_lines, printed_lines):
        if NUMBER.sub("#", a) != NUMBER.sub("#", b):
            return False, f"shown {a!r}, printed {b!r}"
        for x, y in zip(NUMBER.findall(a), NUMBER.findall(b)):
            if abs(float(x) - float(y)) > 1e-5 + 1e-3 * abs(float(x)):
                return False, f"shown {a!r}, printed {b!r}"
    return True, ""


def _environment(block: Block, work: pathlib.Path) -> dict:
    env = dict(
        os.environ, WORK=str(work), PATH=f"{pathlib.Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
    )
    needs = block.directives.get("needs", "")
    if "modelnet40" in needs:
        if not MODELNET_DIR.exists():
            pytest.skip(f"ModelNet40 is not here ({MODELNET_DIR}); it ships with ../shared")
        env["MODELNET40"] = str(MODELNET_DIR)
    if "dragon" in needs:
        if not DRAGON_DIR.exists():
            pytest.skip(f"the dragon scans are not here ({DRAGON_DIR}); they ship with ../shared")
        scans = work / "scans"
        scans.mkdir()
        for angle in (0, 24):
            (scans / f"dragonStandRight_{angle}.ply").symlink_to(DRAGON_DIR / f"dragonStandRight_{angle}.ply")
        env["SCANS"] = str(scans)
    if "3dmatch" in needs:
        if not THREEDMATCH_DIR.exists():
            pytest.skip(f"the 3DMatch scenes are not here ({THREEDMATCH_DIR}); they ship with ../shared")
        env["THREEDMATCH"] = str(THREEDMATCH_DIR)
    return env


#: Entries of the root a page's command may write into, or that a reader's clone does not have.
_NOT_LINKED = {"examples", "runs", "site", ".git", ".venv"}


def reader_root(folder: pathlib.Path) -> pathlib.Path:
    """A fresh stand-in for the root of a clone, where the pages' readers stand: every top-level entry of the
    repository linked, but ``examples/`` copied (commands write beside its files) and nothing that is built."""
    folder.mkdir(parents=True)
    for entry in ROOT.iterdir():
        if entry.name not in _NOT_LINKED and not entry.name.endswith(".egg-info"):
            (folder / entry.name).symlink_to(entry)
    shutil.copytree(ROOT / "examples", folder / "examples")
    return folder


def _commands(block: Block) -> list[str]:
    commands = []
    for line in block.code.split("\n"):
        line = line.split("  #")[0].rstrip()
        if not line or line.startswith("#"):
            continue
        if commands and commands[-1].endswith("\\"):
            commands[-1] = commands[-1][:-1] + " " + line.strip()
        else:
            commands.append(line)
    return commands


#: Runs every Python block of the pages in one process, each in a fresh namespace and its own folder, so the
#: shipped weights load and compile once; prints {block id: [printed, error or None]} as JSON.
_DRIVER = """
import contextlib, io, json, os, sys, traceback
results = {}
for block in json.load(sys.stdin):
    os.chdir(block["cwd"])
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(block["code"], block["id"], "exec"), {"__name__": "__main__"})
        results[block["id"]] = [out.getvalue(), None]
    except BaseException:
        results[block["id"]] = [out.getvalue(), traceback.format_exc()[-3000:]]
print(json.dumps(results))
"""


def test_every_python_block_runs_and_prints_what_the_page_shows(tmp_path):
    """One test for every Python block of the pages, run in one process (see ``_DRIVER``)."""
    import json

    blocks = [b for b in BLOCKS if b.language == "python"]
    payload = []
    for k, block in enumerate(blocks):
        payload.append({"id": block.id, "code": block.code, "cwd": str(reader_root(tmp_path / f"block{k}"))})
    proc = subprocess.run(
        [sys.executable, "-c", _DRIVER],
        input=json.dumps(payload),
        capture_output=True,
        text=True,
        timeout=900,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().split("\n")[-1])
    for block in blocks:
        printed, error = results[block.id]
        assert error is None, f"{block.id}: {error}"
        if block.output is not None:
            ok, why = same_output(block.output, printed)
            assert ok, f"{block.id}: {why}\n{printed}"


@pytest.mark.parametrize("block", [b for b in BLOCKS if b.language == "bash"], ids=lambda b: b.id)
def test_every_command_runs_and_prints_what_the_page_shows(block, tmp_path):
    if "ci" in block.directives:
        ci = (ROOT / ".ci" / "run").read_text()
        assert block.code.strip() in ci, ".ci/run does not run the README's test command as written"
        return
    work = tmp_path / "job"
    work.mkdir()
    env = _environment(block, work)
    cwd = reader_root(tmp_path / "root")
    printed = ""
    for command in _commands(block):
        if command.startswith("python3 -m venv"):
            # A set-up line: the venv and the install are this session's; the job after them runs here.
            command = command.split(" && ")[-1]
        command = f"{command} {block.directives.get('args', '')}".strip()
        proc = subprocess.run(["bash", "-c", command], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"{command}: {proc.stderr[-3000:]}"
        printed += proc.stdout
    if block.output is not None:
        ok, why = same_output(block.output, printed)
        assert ok, f"{block.id}: {why}\n{printed}"


def test_the_pages_have_blocks_and_their_outputs():
    """The runner finds what it should: the README's set-up commands, the register example and its output."""
    readme = [b for b in BLOCKS if b.page == "README.md"]
    assert readme[0].code.startswith("python3 -m venv") and "ci" in readme[1].directives
    # No hidden working folder: a block that needs another one says `cd` in its own text.
    assert not any("cwd" in b.directives for b in BLOCKS)
    assert any(b.output and "trusted" in b.output for b in readme)
    assert same_output("a 1.000 deg, 2.50 s\n", "a 1.0004 deg, 9.99 s\n")[0]
    assert not same_output("a 1.000 deg\n", "a 1.1 deg\n")[0]


def test_the_site_builds_in_strict_mode(tmp_path):
    """mkdocs.yml sets strict: a broken link, a missing page or a docstring the API page cannot render fails."""
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").read_text().count("doc-function") > 50


def test_every_public_function_of_the_api_pages_has_a_docstring():
    modules = re.findall(r"^::: (\S+)$", (ROOT / "docs" / "api.md").read_text(), re.M)
    missing = []
    for name in modules:
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            if attr.startswith("_") or getattr(value, "__module__", None) != name:
                continue
            if (inspect.isfunction(value) or inspect.isclass(value)) and not inspect.getdoc(value):
                missing.append(f"{name}.{attr}")
    assert not missing, f"no docstring: {', '.join(missing)}"


def test_the_generated_tables_are_current():
    """Every table between <!-- results:NAME --> markers is what tools/results_page.py makes of the
    committed results files (nothing is registered)."""
    import results_page

    for name in results_page.TABLES:
        for page in results_page._pages(name):
            now, generated = results_page.render(name, page)
            assert now == generated, f"{page.name}: table {name} is stale; run python tools/results_page.py"
