"""The documentation holds: the README stays a short manual, every relative link and anchor in the Markdown
resolves, every docs/ page is reachable from the README, the commands in the docs name real flags, and the
README's command-line tour runs as written."""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sysconfig
from pathlib import Path

from noisenerf.cli import main as noisenerf_cli, reveal as reveal_cli

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
CHECKED = [README, ROOT / "ARCHITECTURE.md", ROOT / "CHANGELOG.md", *DOCS]
MAX_README_LINES = 300
TOUR_HEADING = "Command-line tour"

FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
INLINE_CODE = re.compile(r"`[^`\n]*`")
INLINE_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s+<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$")
EXTERNAL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")  # http:, https:, mailto:, …


# ---- reading Markdown -------------------------------------------------------------------------------------

def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(line)
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: link text kept, lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file, repeated headings numbered as GitHub does (x, x-1, x-2)."""
    seen: dict[str, int] = {}
    result = set()
    for line in prose_lines(path.read_text()):
        match = HEADING.match(line)
        if match:
            base = slug(match.group(2))
            count = seen.get(base, 0)
            seen[base] = count + 1
            result.add(base if count == 0 else f"{base}-{count}")
    return result


def links(path: Path) -> list[str]:
    """Every link target in a Markdown file's prose (inline links, images and reference definitions)."""
    targets = []
    for line in prose_lines(path.read_text()):
        reference = REFERENCE_LINK.match(line)
        if reference:
            targets.append(reference.group(1))
        targets += INLINE_LINK.findall(INLINE_CODE.sub("", line))
    return targets


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """The relative links of `path` whose file or heading does not exist, each as 'FILE: TARGET (why)', FILE
    relative to `root`."""
    broken = []
    for target in links(path):
        if EXTERNAL.match(target):
            continue
        file_part, _, anchor = target.partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path
        where = f"{path.relative_to(root)}: {target}"
        if not resolved.exists():
            broken.append(f"{where} (no such file)")
        elif anchor and (resolved.suffix != ".md" or anchor not in anchors(resolved)):
            broken.append(f"{where} (no heading #{anchor} in {resolved.name})")
    return broken


def section(path: Path, heading: str) -> str:
    """The text under `## heading` up to the next level-2 heading."""
    text = path.read_text()
    marker = f"\n## {heading}\n"
    assert marker in text, f"{path.name} has no '## {heading}' section"
    return text.split(marker, 1)[1].split("\n## ", 1)[0]


def code_blocks(text: str, languages=("bash", "sh", "shell")) -> list[str]:
    """The bodies of the fenced code blocks in `text` whose info string is one of `languages`."""
    blocks, body, language = [], None, None
    for line in text.splitlines():
        match = FENCE.match(line)
        if match and body is None:
            language, body = line.strip()[3:].strip(), []
        elif match:
            if language in languages:
                blocks.append("\n".join(body))
            body = None
        elif body is not None:
            body.append(line)
    return blocks


def commands(block: str) -> list[str]:
    """A shell block's commands: backslash continuations joined, blank and comment-only lines left out."""
    joined = block.replace("\\\n", " ")
    return [line.strip() for line in joined.splitlines() if line.strip() and not line.strip().startswith("#")]


# ---- the README stays short, the links resolve ---------------------------------------------------------------

def test_the_readme_is_a_short_manual():
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; at most {MAX_README_LINES}"


def test_every_relative_link_and_anchor_resolves():
    checked = [path for path in CHECKED if path.exists()]
    assert README in checked and len(DOCS) >= 1, "README.md and the docs/ pages must exist"
    assert sum(len(links(path)) for path in checked) >= len(DOCS), "no links found: is the link pattern right?"
    broken = [problem for path in checked for problem in broken_links(path)]
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_every_docs_page_is_linked_from_the_readme():
    linked = {(README.parent / target.partition("#")[0]).resolve()
              for target in links(README) if not EXTERNAL.match(target) and target.partition("#")[0]}
    unlinked = [page.name for page in DOCS if page.resolve() not in linked]
    assert not unlinked, f"docs pages the README does not link: {unlinked}"


def test_the_link_checker_sees_a_broken_link_and_anchor(tmp_path):
    """The checker itself: a missing file and a missing heading are reported, a good anchor is not."""
    page = tmp_path / "page.md"
    (tmp_path / "other.md").write_text("# Other\n\n## The paper's method ÷ 2\n")
    page.write_text("[a](other.md#the-papers-method--2) [b](missing.md) [c](other.md#nope) `[d](gone.md)`\n"
                    "```\n[e](gone.md)\n```\n[f](https://example.com/x)\n")
    broken = [problem.split(": ", 1)[1] for problem in broken_links(page, root=tmp_path)]
    assert broken == ["missing.md (no such file)", "other.md#nope (no heading #nope in other.md)"], broken


# ---- the commands in the docs name real flags -------------------------------------------------------------------

def known_options() -> dict[str, set[str]]:
    """Option strings by program ('noisenerf SUBCOMMAND' or 'noisenerf-reveal'), from the parsers themselves."""
    options = {"noisenerf-reveal": {o for a in reveal_cli.build_parser()._actions for o in a.option_strings}}
    parser = noisenerf_cli.build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subparsers.choices.items():
        options[f"noisenerf {name}"] = {o for a in sub._actions for o in a.option_strings}
    return options


def invocations(block: str) -> list[tuple[str, list[str]]]:
    """(program, flags) of each `noisenerf …` or `noisenerf-reveal …` in a shell block. A synopsis's indented
    lines continue the command above them; comments, and the words before the program (an environment
    assignment, `sh -c '`) are left out."""
    lines: list[str] = []
    for line in block.replace("\\\n", " ").splitlines():
        if lines and line[:1].isspace() and line.strip():
            lines[-1] += " " + line.strip()
        else:
            lines.append(line)
    found = []
    for line in lines:
        line = re.split(r"\s#", line, maxsplit=1)[0]
        for segment in re.split(r"&&|;", line):
            words = segment.replace("'", " ").replace('"', " ").split()
            programs = [i for i, word in enumerate(words) if word in ("noisenerf", "noisenerf-reveal")]
            if not programs:
                continue
            start = programs[0]
            program = words[start]
            rest = words[start + 1:]
            if program == "noisenerf":
                program, rest = f"noisenerf {rest[0] if rest else ''}", rest[1:]
            flags = re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", " ".join(rest))
            found.append((program, flags))
    return found


def test_the_commands_in_the_docs_use_real_subcommands_and_flags():
    options = known_options()
    seen, unknown = 0, []
    for path in (README, *DOCS):
        for block in code_blocks(path.read_text()):
            for program, flags in invocations(block):
                seen += 1
                if program not in options:
                    unknown.append(f"{path.name}: {program}")
                    continue
                unknown += [f"{path.name}: {program} {flag}" for flag in flags if flag not in options[program]]
    assert seen >= 10, f"only {seen} noisenerf commands found in the docs' shell blocks"
    assert not unknown, "commands or flags the command lines do not have:\n" + "\n".join(unknown)


def test_the_flag_check_sees_an_unknown_flag():
    flags = dict(invocations("noisenerf hide S x.png -o b --view 2 --nope\n"
                             "    [--recipe authors|paper]   # paper\n"
                             "X=1 noisenerf-reveal m b -o o --json && ray start --head"))
    assert flags == {"noisenerf hide": ["-o", "--view", "--nope", "--recipe"], "noisenerf-reveal": ["-o", "--json"]}


# ---- the README's command-line tour runs as written ---------------------------------------------------------------

ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


def outputs(command: str) -> list[str]:
    """The files a command names as its outputs: after -o/--output, and shell redirections (> and >>)."""
    words = shlex.split(command, comments=True)
    named = [words[i + 1] for i, word in enumerate(words[:-1]) if word in ("-o", "--output", ">", ">>")]
    return named + [word.split("=", 1)[1] for word in words if word.startswith("--output=")]


def test_the_readme_tour_runs_as_written(tmp_path):
    blocks = code_blocks(section(README, TOUR_HEADING))
    assert blocks, f"no ```bash block under '## {TOUR_HEADING}' in README.md"
    tour = commands(blocks[0])
    words = " ".join(tour)
    for step in ("noisenerf export", "noisenerf hide", "noisenerf-reveal"):
        assert step in words, f"the tour no longer runs `{step}`"

    scripts = Path(sysconfig.get_path("scripts"))
    assert (scripts / "noisenerf").exists() and (scripts / "noisenerf-reveal").exists(), \
        f"noisenerf's command lines are not installed in {scripts}"
    env = {key: value for key, value in os.environ.items() if key != "NOISENERF_PASSPHRASE"}
    env["PATH"] = f"{scripts}{os.pathsep}{env.get('PATH', '')}"

    assignments: list[str] = []
    for command in tour:
        script = "\n".join(["set -euo pipefail", *assignments, command])
        result = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                                timeout=300, stdin=subprocess.DEVNULL)
        assert result.returncode == 0, f"`{command}` exited {result.returncode}:\n{result.stderr[-2000:]}"
        for name in outputs(command):
            assert (tmp_path / name).exists(), f"`{command}` did not write {name}"
        if "--json" in shlex.split(command, comments=True):
            report = json.loads(result.stdout)
            assert report.get("exact", True) is True, f"`{command}`: {report}"
        if ASSIGNMENT.match(command):
            assignments.append(command)
