"""The documentation holds together: links resolve, the README stays short, the README's
test command is the one CI runs, every command's --help names its guide page, and code and
docs cite the paper and the public code directly, never notes outside the repository or an
issue number."""
from __future__ import annotations

import argparse
import json
import importlib
import importlib.util
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from e3dpsm.cli import COMMANDS, DOCS, main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_MAX_LINES = 160
MARKER = "<!-- test-command -->"

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def doc_files() -> list[Path]:
    return [README, *sorted((ROOT / "docs").glob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in FENCE.sub("", path.read_text(encoding="utf-8")).splitlines():
        match = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")
    return out


def broken_links(path: Path) -> list[str]:
    text = INLINE_CODE.sub("", FENCE.sub("", path.read_text(encoding="utf-8")))
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path
        if not resolved.exists():
            broken.append(f"{target} (no file {resolved})")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target} (no heading #{anchor} in {resolved.name})")
    return broken


def test_docs_folder_has_pages():
    pages = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert "index.md" in pages
    assert set(Path(p).name for p in DOCS.values()) <= pages


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(path):
    assert broken_links(path) == [], f"broken links in {path.relative_to(ROOT)}"


def test_link_checker_sees_a_broken_link(tmp_path):
    (tmp_path / "a.md").write_text("# Title\n\n[ok](a.md#title) [bad](missing.md) [anchor](a.md#nope)\n"
                                   "```\n[in code](ignored.md)\n```\n")
    broken = broken_links(tmp_path / "a.md")
    assert len(broken) == 2 and "missing.md" in broken[0] and "#nope" in broken[1]


def test_slug_matches_github():
    assert slug("FLOPs, memory, latency, Hz: `e3dpsm profile`") == "flops-memory-latency-hz-e3dpsm-profile"
    assert slug("`paper`, `released` and the paper text") == "paper-released-and-the-paper-text"


def test_readme_is_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move detail into docs/"


def readme_test_command_python(text: str) -> str:
    """The line after the marker, skipping code-fence lines (what .ci/run's awk does)."""
    lines = text.splitlines()
    index = next(i for i, line in enumerate(lines) if MARKER in line) + 1
    while index < len(lines) and lines[index].startswith("```"):
        index += 1
    return lines[index] if index < len(lines) else ""


def ci_awk_program() -> str:
    """The awk program .ci/run uses to read the test command, taken from .ci/run itself."""
    script = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    match = re.search(r"awk\s+'([^']*)'\s+README\.md", script)
    assert match, ".ci/run no longer reads the test command with awk from README.md"
    return match.group(1)


def test_readme_test_command_is_what_ci_runs():
    ci_command = subprocess.run(["awk", ci_awk_program(), str(README)], capture_output=True, text=True,
                                check=True).stdout.rstrip("\n")
    ours = readme_test_command_python(README.read_text(encoding="utf-8"))
    assert ci_command == ours
    argv = shlex.split(ci_command)
    assert argv[:3] == ["python", "-m", "pytest"], ci_command


def test_readme_first_block_installs_cpu_torch_first():
    text = README.read_text(encoding="utf-8")
    first = FENCE.search(text)
    assert first, "README.md has no command block"
    block = first.group(0)
    tokens = [t for line in block.splitlines()[1:-1] for t in shlex.split(line)]
    torch_at = tokens.index("torch==2.13.0") if "torch==2.13.0" in tokens else None
    editable_at = next((i + 1 for i, t in enumerate(tokens[:-1]) if t == "-e" and tokens[i + 1].startswith(".")),
                       None)
    assert torch_at is not None and editable_at is not None, block
    assert torch_at < editable_at, f"torch==2.13.0 must be installed before -e .: {block}"


# Citations point at what a reader can open: the paper (section, equation, table) or the public
# code (URL and path), gathered in docs/model.md#citations. Two kinds of pointer cannot be
# followed from a clone: the development setup's reference notes (a file outside the
# repository) and issue numbers. benchmarks/results/ holds records and is left as written.
CITATION_RULES: dict[str, re.Pattern[str]] = {
    "cites the reference notes outside the repository; cite the paper or the public code "
    "(docs/model.md#citations)": re.compile(r"\bFACTS\b"),
    "names an issue number; say what it is about instead": re.compile(r"\b[Ii]ssues?\s*#?\d"),
}
CITATION_SUFFIXES = (".py", ".md", ".toml")
RECORDS = "benchmarks/results/"


def citation_problems(text: str) -> list[str]:
    """'line N: what is wrong: the line' for every line that breaks a citation rule."""
    return [f"line {number}: {why}: {line.strip()}"
            for number, line in enumerate(text.splitlines(), 1)
            for why, pattern in CITATION_RULES.items() if pattern.search(line)]


def cited_sources() -> list[str]:
    """Tracked .py, .md and .toml files (repository-relative), records excluded."""
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout: {listed.stderr.strip()}")
    return [name for name in listed.stdout.split("\0")
            if name.endswith(CITATION_SUFFIXES) and not name.startswith(RECORDS) and (ROOT / name).is_file()]


def test_code_and_docs_cite_directly():
    sources = cited_sources()
    assert "docs/model.md" in sources and "e3dpsm/layers/fusion.py" in sources  # the listing works
    problems = {name: citation_problems((ROOT / name).read_text(encoding="utf-8")) for name in sources}
    problems = {name: found for name, found in problems.items() if found}
    assert problems == {}, "\n".join(f"{name} {p}" for name, found in problems.items() for p in found)


def test_citation_checker_bites():
    notes, issue = "FAC" + "TS", "iss" + "ue"  # split so this file passes its own check
    for bad in (f"(see {notes} section 3)", f"{notes}.md", f"at its edges ({issue} 25, part 6)",
                f"({issue}s 24 and 27)", f"{issue.capitalize()} 24's route", f"{issue} #14", f"{issue}14"):
        assert len(citation_problems(f"ok\n{bad}\n")) == 1, bad
    assert citation_problems(f"a\nb ({notes} section 4)")[0].startswith("line 2: cites the reference notes")
    # near misses: other words that contain the letters, and an issue without a number
    for fine in ("_ARTIFACTS = (CHECKPOINT_NAME,)", "ARTIFACTS[fmt]", "facts from the paper", "a tissue 3 mm thick",
                 f"the {issue}'s 20% bar", "paper Sec. 4.2, Eq. 16; docs/model.md#citations, Kalman fusion"):
        assert citation_problems(fine) == [], fine


def cli_names() -> dict[str, str]:
    """Module name in COMMANDS -> the command users type, read from each module's parser."""
    sub = argparse.ArgumentParser(prog="e3dpsm").add_subparsers()
    names = {}
    for name in COMMANDS:
        module = f"e3dpsm.cli.{name}"
        if importlib.util.find_spec(module) is not None:
            names[name] = importlib.import_module(module).register(sub).prog.split()[-1]
    return names


def test_every_command_has_a_guide_page():
    assert set(DOCS) == set(COMMANDS), "DOCS in e3dpsm/cli/__init__.py maps exactly the commands in COMMANDS"
    for name, cli in cli_names().items():
        page = ROOT / DOCS[name]
        assert page.is_file(), f"{cli}: {DOCS[name]} does not exist"
        assert f"e3dpsm {cli}" in page.read_text(encoding="utf-8"), f"{DOCS[name]} never mentions e3dpsm {cli}"
        assert f"e3dpsm {cli}" in README.read_text(encoding="utf-8"), f"README's table lacks e3dpsm {cli}"


@pytest.mark.parametrize("name", COMMANDS)
def test_help_names_the_guide(name, capsys):
    cli = cli_names().get(name)
    if cli is None:
        pytest.skip(f"e3dpsm.cli.{name} is not installed")
    with pytest.raises(SystemExit) as exit_:
        main([cli, "--help"])
    assert exit_.value.code == 0
    assert f"Guide: {DOCS[name]}" in capsys.readouterr().out


def test_help_of_an_action_names_the_guide(capsys):
    with pytest.raises(SystemExit):
        main(["golden", "record", "--help"])
    assert "Guide: docs/golden-and-diagnose.md" in capsys.readouterr().out


def test_console_help_names_the_guide():
    out = subprocess.run([sys.executable, "-m", "e3dpsm", "quantize", "--help"], capture_output=True,
                         text=True, check=True, cwd=ROOT).stdout
    assert "Guide: docs/quantize.md" in out


INT8_RESULTS = ROOT / "benchmarks" / "results" / "int8_small_vnni.json"


def _bench_int8():
    spec = importlib.util.spec_from_file_location("bench_int8", ROOT / "benchmarks" / "bench_int8.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _flat(text: str) -> str:
    return " ".join(text.split())


def test_readme_int8_figures_are_the_results_files():
    """README's INT8 sentence is the one benchmarks/bench_int8.py writes from its results file:
    every figure in it (budget changes, bounds, frames, size, nodes, speeds) comes from there."""
    result = json.loads(INT8_RESULTS.read_text(encoding="utf-8"))
    sentence = _bench_int8().headline(result)
    assert _flat(sentence) in _flat((ROOT / "README.md").read_text(encoding="utf-8"))
    # the check bites: one figure changed in the results is no longer README's sentence
    rows = result["rows"]
    rows[0]["size_ratio"] += 0.01
    assert _flat(_bench_int8().headline(result)) not in _flat((ROOT / "README.md").read_text(encoding="utf-8"))
