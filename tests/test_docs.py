"""The README and docs/ hold to what the code does.

- The README stays short, and its quick start is the first section with exactly two commands
  (the second is what `.ci/run` runs).
- Every relative link in README.md and docs/*.md points to a file that exists (and to a heading
  of it, when the link names one).
- Every ```python block runs as it is, from a temporary folder holding copies of
  experiments/configs/ and checkpoints/ (so nothing is written into the repository), with a
  compiled-code cache of the session's own: each in a process of its own, forked from one that
  has imported only third-party modules (torch, numpy, matplotlib: 2 to 4 s in every block).
- Every `torchfric SUBCOMMAND` in a command line names a real subcommand.
- Every message quoted in docs/troubleshooting.md is the code's own text.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import select
import shutil
import signal
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
README_MAX_LINES = 250
# Subcommands being built beside the parser's own; every other name must be in the parser.
PLANNED_SUBCOMMANDS = {"init", "check"}

FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.S | re.M)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
INLINE_CODE = re.compile(r"`([^`\n]+)`")
# a command: `torchfric WORD` at the start of a line or code span, or in a block after &&, ;, |
# or $ (a span such as `… is not a torchfric checkpoint; torchfric refuses …` is a message)
SUBCOMMAND = re.compile(r"(?:^|&&|;|\||\$)[ \t]*torchfric[ \t]+([a-z][\w-]*)", re.M)
SPAN_COMMAND = re.compile(r"^[ \t]*torchfric[ \t]+([a-z][\w-]*)")


def _rel(page: pathlib.Path) -> str:
    return str(page.relative_to(ROOT))


def _fences(text: str) -> list[tuple[str, str]]:
    """``(tag, body)`` of every fenced block."""
    return [(m.group(1).strip(), m.group(2)) for m in FENCE.finditer(text)]


def _prose(text: str) -> str:
    """`text` without its fenced blocks."""
    return FENCE.sub("", text)


def _python_blocks() -> list[tuple[str, int, str]]:
    out = []
    for page in PAGES:
        blocks = [body for tag, body in _fences(page.read_text()) if tag == "python"]
        out += [(_rel(page), i, body) for i, body in enumerate(blocks)]
    return out


def test_readme_is_short() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines; at most {README_MAX_LINES}: move detail to docs/"
    )


def test_quick_start_is_the_first_section_with_two_commands() -> None:
    text = README.read_text()
    sections = re.split(r"^## ", text, flags=re.M)
    assert len(sections) > 1, "README.md has no ## section"
    first = sections[1]
    assert first.splitlines()[0].strip() == "Quick start", "the first ## section is not Quick start"
    blocks = _fences(first)
    assert len(blocks) == 1, f"Quick start holds {len(blocks)} fenced blocks, not one"
    tag, body = blocks[0]
    assert tag == "bash"
    commands = [line for line in body.splitlines() if line.strip()]
    assert len(commands) == 2, f"Quick start holds {len(commands)} command lines, not two"
    install_and_train, install_and_test = commands
    assert "pip install" in install_and_train and "torchfric train" in install_and_train
    assert '".[test]"' in install_and_test and "pytest" in install_and_test
    # CI runs exactly the README's test command
    assert install_and_test in (ROOT / ".ci" / "run").read_text().splitlines()


def _anchors(page: pathlib.Path) -> set[str]:
    """The anchors of a Markdown page's headings, as GitHub makes them."""
    out = set()
    for title in re.findall(r"^#{1,6} (.+)$", _prose(page.read_text()), flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        out.add(slug)
    return out


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_relative_links_point_to_files(page: pathlib.Path) -> None:
    text = INLINE_CODE.sub("", _prose(page.read_text()))
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):
            continue  # a URL
        path, _, anchor = target.partition("#")
        file = (page.parent / path) if path else page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            broken.append(target)
    assert not broken, f"{_rel(page)}: links to missing files or headings: {broken}"


def test_anchors_are_githubs() -> None:
    assert _anchors(ROOT / "docs" / "troubleshooting.md") >= {
        "config-files-and---set",
        "divergence-and-doubtful-results",
    }


def test_the_link_check_sees_links() -> None:
    """The link pattern finds plain links, image links and links with anchors."""
    text = "see [a](docs/a.md), ![fig](x/y.png) and [b](b.md#part) but not `[c](c.md)`"
    assert LINK.findall(INLINE_CODE.sub("", text)) == ["docs/a.md", "x/y.png", "b.md#part"]


def _subcommands(text: str) -> set[str]:
    """The subcommands of the commands written in `text`: in its non-Python fenced blocks
    (without their comments) and in its inline code spans that are a command."""
    blocks = [body for tag, body in _fences(text) if not tag.startswith("python")]
    found = set()
    for body in blocks:
        found |= set(SUBCOMMAND.findall(re.sub(r"(^|\s)#.*$", "", body, flags=re.M)))
    for span in INLINE_CODE.findall(_prose(text)):
        found |= set(SPAN_COMMAND.findall(span))
    return found


def _known_subcommands() -> set[str]:
    import argparse

    from torchfric.app.cli import build_parser

    actions = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return set(actions[0].choices) | PLANNED_SUBCOMMANDS


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_documented_subcommands_exist(page: pathlib.Path) -> None:
    known = _known_subcommands()
    used = _subcommands(page.read_text())
    assert used or page != README, "README.md shows no torchfric command"
    assert used <= known, f"{_rel(page)}: no such subcommand(s) {sorted(used - known)}"


def test_the_subcommand_check_sees_commands() -> None:
    text = (
        "run `torchfric train my.toml`, not `a torchfric checkpoint`, or\n\n```bash\n"
        "pip install -e . && torchfric check X\ntorchfric frobnicate X  # torchfric needed\n```\n"
    )
    assert _subcommands(text) == {"train", "check", "frobnicate"}
    assert "frobnicate" not in _known_subcommands()


def _source_text() -> str:
    """Every torchfric module, with adjacent string literals joined (a message split over
    lines reads as one string)."""
    src = "\n".join(p.read_text() for p in sorted((ROOT / "torchfric").rglob("*.py")))
    return re.sub(r"[\"']\s*\n\s*(?:[rRbBfFuU]{1,2})?[\"']", "", src)


def _quoted_messages() -> list[str]:
    """The first cell of every table row in docs/troubleshooting.md, when it is code."""
    text = (ROOT / "docs" / "troubleshooting.md").read_text()
    return re.findall(r"^\| `([^`]+)` \|", text, flags=re.M)


def test_troubleshooting_quotes_real_messages() -> None:
    messages = _quoted_messages()
    assert len(messages) > 100
    source = _source_text()
    invented = []
    for message in messages:
        parts = [p.strip(" …") for p in message.split("…")]
        assert any(len(p) >= 8 for p in parts), f"too little of the message to check: {message!r}"
        if not all(p in source for p in parts if len(p) >= 4):
            invented.append(message)
    assert not invented, f"not the code's text (or since changed): {invented}"


# The snippet runner: `python -c` that imports torch, numpy and matplotlib once, then forks a
# child per block. The child runs the block as `python -c BLOCK` would: in a clean `__main__`,
# from the block's folder, its stdout and stderr in files, its exit status that of the block (a
# traceback and 1 on an exception; SystemExit's code); atexit handlers and non-daemon threads
# end first.
RUNNER = r"""
import json, os, sys
# imported before the fork, third-party modules only: what the blocks import again and again
# (torch._inductor, 1.7 s: torchfric's compiled paths import it; matplotlib: the run's figures)
import matplotlib.backends.backend_agg, matplotlib.figure, numpy, torch, torch._inductor  # noqa


def run(job):
    import atexit, builtins, os, sys, threading, traceback  # locals: the globals are cleared
    os.chdir(job["cwd"])
    for fd, name in ((1, "out"), (2, "err")):
        os.dup2(os.open(job[name], os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
    os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
    main = sys.modules["__main__"].__dict__
    main.clear()
    main.update(__name__="__main__", __builtins__=builtins, __doc__=None, __spec__=None,
                __loader__=None, __package__=None)
    code = 0
    try:
        exec(compile(job["code"], "<string>", "exec"), main)
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
        if not isinstance(stop.code, int) and stop.code is not None:
            print(stop.code, file=sys.stderr)
    except BaseException:
        traceback.print_exc()
        code = 1
    threading._shutdown()
    atexit._run_exitfuncs()
    sys.stdout.flush(), sys.stderr.flush()
    os._exit(code)


for line in sys.stdin:
    pid = os.fork()
    if pid == 0:
        try:
            run(json.loads(line))
        finally:
            os._exit(70)  # run failed itself: never back into this loop
    print(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]), flush=True)
"""


@pytest.fixture(scope="module")
def snippet_runner(worker_cache_dir: pathlib.Path):  # type: ignore[no-untyped-def]
    env = {**os.environ, "TORCHFRIC_CACHE": str(worker_cache_dir)}  # one build per worker
    env.pop("TORCHFRIC_NATIVE", None)
    runner = subprocess.Popen([sys.executable, "-c", RUNNER], env=env, text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              start_new_session=True)  # fmt: skip

    def run(code: str, cwd: pathlib.Path, timeout: float = 600.0) -> tuple[int, str]:
        out, err = cwd.parent / "stdout.txt", cwd.parent / "stderr.txt"
        job = {"code": code, "cwd": str(cwd), "out": str(out), "err": str(err)}
        runner.stdin.write(json.dumps(job) + "\n")
        runner.stdin.flush()
        if not select.select([runner.stdout], [], [], timeout)[0]:
            os.killpg(runner.pid, signal.SIGKILL)  # the runner and the block's process
            pytest.fail(f"the block ran past {timeout:g} s")
        line = runner.stdout.readline()
        assert line, "the snippet runner died"
        return int(line), err.read_text() if err.exists() else ""

    yield run
    runner.stdin.close()
    runner.wait(timeout=60)


@pytest.mark.parametrize(
    ("page", "index", "code"), _python_blocks(), ids=[f"{p}[{i}]" for p, i, _ in _python_blocks()]
)
def test_python_snippet_runs(page: str, index: int, code: str, tmp_path, snippet_runner) -> None:  # type: ignore[no-untyped-def]
    work = tmp_path / "work"  # the block's folder; its stdout and stderr are kept beside it
    shutil.copytree(ROOT / "experiments" / "configs", work / "experiments" / "configs")
    shutil.copytree(ROOT / "checkpoints", work / "checkpoints")
    returncode, stderr = snippet_runner(code, work)
    assert returncode == 0, f"{page} python block {index} failed:\n{stderr[-3000:]}"
