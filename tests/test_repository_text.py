"""The repository's own text: no diary wording, no dead links, README commands that parse.

    pytest -q tests/test_repository_text.py

Four checks over what a clean clone holds:

- every tracked text file (``git ls-files``; binaries skipped) is free of development-diary
  wording: a result is dated (2026-11-26) or tied to a commit, never to the working stop, session
  or day it was measured in, which mean nothing to a reader (DIARY_PATTERNS; this file spells its
  own examples in two pieces so that it passes its own check);
- README.md and docs/*.md: every relative link and image exists (an anchor into a markdown page
  names one of its headings), and every repository path they name (``docs/...``,
  ``baselines/...``, ``reflow_plugin/...``, any tracked top-level folder) exists (a removed
  module is named with its commit, ``e676122:reflow_plugin/promotion.py``, and not checked);
- docs/ARCHITECTURE.md's module map: a module named in a package's section exists in that package;
- every ``python ...`` line in the README's code blocks names a script or module whose
  ``--help`` works, and each flag it types is one that ``--help`` lists (one subprocess runs
  every ``--help``, so torch is imported once).

Each check's detector is also tested on planted text, so a detector that finds nothing fails.
"""
from __future__ import annotations

import itertools
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Diary wording, case-insensitive. "stop" alone is a rasterizer word (the transmittance stop), so
# only a numbered stop or one named by a determiner of time counts; pytest's scope="session" and
# "once per session" do not match the session pattern.
DIARY_PATTERNS = (
    r"\bstops?[- ]?\d+\b",
    r"\b(?:this|that|next|previous|last|each) stop\b",
    r"\b(?:this|that|previous|last|next|same|one|later|earlier|first|second|third|fourth|fifth|two"
    r"|three|a|another) (?:gpu )?sessions?\b",
    r"\btoday\b",
    r"\byesterday\b",
    r"\bthis round\b",
)
DIARY = re.compile("|".join(DIARY_PATTERNS), re.IGNORECASE)


def diary_hits(text: str) -> list[tuple[int, str]]:
    """(line number, matched words) for every piece of diary wording in `text`."""
    return [(number, match.group(0)) for number, line in enumerate(text.splitlines(), 1)
            for match in DIARY.finditer(line)]


def tracked_text_files(root: Path) -> list[Path]:
    """The files git tracks under `root` that decode as UTF-8 text (no NUL byte)."""
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=False)
    if listed.returncode != 0:
        pytest.skip(f"not a git checkout ({listed.stderr.decode().strip()})")
    files = []
    for name in listed.stdout.decode().split("\0"):
        path = root / name
        if not name or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue
        try:
            data.decode("utf-8")
        except UnicodeDecodeError:
            continue
        files.append(path)
    return files


# ---------------------------------------------------------------------------- links and paths

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def _without_code(text: str) -> str:
    """`text` with fenced code blocks blanked (a link inside one is not a link)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else line)
    return "\n".join(out)


def heading_anchors(text: str) -> set[str]:
    """GitHub's anchors of the markdown headings in `text` (duplicates get -1, -2, ...)."""
    anchors: set[str] = set()
    seen: dict[str, int] = {}
    for line in _without_code(text).splitlines():
        match = HEADING.match(line)
        if not match:
            continue
        slug = re.sub(r"[^\w\- ]", "", match.group(2).strip().lower()).replace(" ", "-")
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        anchors.add(slug if count == 0 else f"{slug}-{count}")
    return anchors


def dead_links(page: Path, text: str) -> list[str]:
    """Relative links and images of the markdown `page` (content `text`) that lead nowhere."""
    dead = []
    for target in LINK.findall(_without_code(text)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        linked = (page.parent / path_part).resolve() if path_part else page
        if not linked.exists():
            dead.append(f"{target} (no such file)")
        elif anchor and linked.suffix == ".md":
            if anchor not in heading_anchors(linked.read_text(encoding="utf-8")):
                dead.append(f"{target} (no heading with that anchor)")
    return dead


def _expand_braces(path: str) -> list[str]:
    match = re.search(r"\{([^{}]*)\}", path)
    if not match:
        return [path]
    return list(itertools.chain.from_iterable(
        _expand_braces(path[:match.start()] + option + path[match.end():]) for option in match.group(1).split(",")))


def named_paths(text: str, folders: set[str]) -> list[str]:
    """Repository paths named in `text`: tokens that start with a tracked top-level folder. A path
    written as git's `COMMIT:path` names a file of that commit (the record of a removed module)
    and is not one of them."""
    if not folders:
        return []
    alternatives = "|".join(sorted(re.escape(folder) for folder in folders))
    pattern = re.compile(rf"(?<![\w/.~:-])((?:{alternatives})/[\w./{{}},*-]*)")
    paths = []
    for token in pattern.findall(text):
        for path in _expand_braces(token.rstrip(".,:;")):
            if "*" not in path:
                paths.append(path)
    return paths


def missing_paths(text: str, root: Path, folders: set[str]) -> list[str]:
    """The repository paths named in `text` that do not exist under `root`."""
    return sorted({path for path in named_paths(text, folders) if not (root / path).exists()})


def module_map_gaps(text: str, files: set[str]) -> list[str]:
    """Module files named in the sections of a module map that are headed by a package
    (``## `baselines/render`: ...``) that no file of that package's top folder is: such a
    section names its modules relative to the package (`kernel.py`, `fourdgs/interrupt.py`) or
    by their repository path."""
    gaps, top = [], None
    for line in text.splitlines():
        heading = re.match(r"^## `([\w/]+)`", line)
        if heading or line.startswith("## "):
            top = heading.group(1).split("/")[0] if heading else None
            continue
        if top is None:
            continue
        for name in re.findall(r"`([\w/]+\.(?:py|cpp))`", line):
            if name not in files and not any(path.startswith(top + "/") and path.endswith("/" + name) for path in files):
                gaps.append(f"{name} (section of {top}/)")
    return gaps


def _top_level_folders(files: list[Path], root: Path) -> set[str]:
    return {path.relative_to(root).parts[0] for path in files if len(path.relative_to(root).parts) > 1}


def _doc_pages(root: Path) -> list[Path]:
    return [root / "README.md"] + sorted((root / "docs").glob("*.md"))


# ---------------------------------------------------------------------------- README commands


def code_block_lines(markdown: str) -> list[str]:
    """The lines of `markdown`'s code blocks (fenced, or indented 4 spaces after a blank line)."""
    lines, fenced, indented, previous_blank = [], False, False, True
    for line in markdown.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            lines.append(line)
            continue
        if line.startswith("    ") and (indented or previous_blank):
            indented = True
            lines.append(line[4:])
        elif line.strip():
            indented = False
        previous_blank = not line.strip()
    return lines


def python_commands(markdown: str) -> list[list[str]]:
    """Every `python ...` command of `markdown`'s code blocks as shell tokens (comments dropped,
    continuation lines joined, leading VAR=value assignments skipped)."""
    commands, pending = [], ""
    for line in code_block_lines(markdown):
        pending += line.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        line, pending = pending, ""
        if not re.match(r"^\s*(?:[A-Z_][A-Z0-9_]*=\S*\s+)*python3?\s", line):
            continue  # other shells' lines (output listings, bash) may not even tokenize
        tokens = shlex.split(line, comments=True)
        while tokens and re.match(r"^[A-Z_][A-Z0-9_]*=", tokens[0]):
            tokens = tokens[1:]
        if tokens and tokens[0] in ("python", "python3"):
            commands.append(tokens)
    return commands


def command_target(tokens: list[str]) -> tuple[str, str, list[str]]:
    """("module" | "script", its name, the arguments) of a `python ...` command's tokens."""
    rest = tokens[1:]
    if rest and rest[0] == "scripts/with_venv.py":  # the environment wrapper runs what follows
        rest = rest[1:]
    if len(rest) >= 2 and rest[0] == "-m":
        return "module", rest[1], rest[2:]
    if rest and rest[0].endswith(".py"):
        return "script", rest[0], rest[1:]
    raise ValueError(f"not a script or module command: {' '.join(tokens)}")


def typed_flags(arguments: list[str]) -> list[str]:
    """The option flags among `arguments` (negative numbers are values, `--x=v` is `--x`)."""
    return [argument.split("=", 1)[0] for argument in arguments
            if argument.startswith("-") and argument != "--" and not re.match(r"^-\d", argument)]


def unlisted_flags(flags: list[str], help_text: str) -> list[str]:
    """The `flags` that `help_text` (an argparse --help) does not list as an option."""
    return [flag for flag in flags if not re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", help_text)]


HELP_DRIVER = r"""
import contextlib, io, json, os, runpy, sys
results = []
for kind, target, argv in json.loads(sys.stdin.read()):
    out = io.StringIO()
    code = 0
    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = [target] + argv
    if kind == "script":
        sys.path.insert(0, os.path.dirname(os.path.abspath(target)))
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            if kind == "module":
                runpy.run_module(target, run_name="__main__", alter_sys=True)
            else:
                runpy.run_path(target, run_name="__main__")
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException as exc:  # reported, not raised: the other commands still run
        code, out = 1, io.StringIO(out.getvalue() + f"{type(exc).__name__}: {exc}")
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
    results.append({"code": code, "output": out.getvalue()})
print(json.dumps(results))
"""


def help_texts(requests: list[tuple[str, str, list[str]]], root: Path) -> list[dict]:
    """Run every (kind, target, argv) with `--help` appended in one fresh interpreter."""
    payload = json.dumps([[kind, target, argv + ["--help"]] for kind, target, argv in requests])
    done = subprocess.run([sys.executable, "-c", HELP_DRIVER], input=payload, cwd=root,
                          capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def help_request(kind: str, target: str, arguments: list[str]) -> tuple[str, str, tuple[str, ...]]:
    """The --help call that lists what `arguments` may use: a plugin's flags appear only with it."""
    argv = []
    if target == "train.py" and "--plugin" in arguments:
        argv = ["--plugin", arguments[arguments.index("--plugin") + 1]]
    return kind, target, tuple(argv)


_HELP_CACHE: dict[tuple[str, str, tuple[str, ...]], dict] = {}  # (kind, target, argv) -> --help result


def command_problems(commands: list[list[str]], root: Path) -> list[str]:
    """One line per README command whose --help fails or that types a flag its --help lacks."""
    checks = []  # (command, request, flags to find in that request's help)
    for tokens in commands:
        kind, target, arguments = command_target(tokens)
        own, passed_on = arguments, []
        if "--" in arguments:
            split = arguments.index("--")
            own, passed_on = arguments[:split], arguments[split + 1:]
        checks.append((tokens, help_request(kind, target, own), typed_flags(own)))
        if passed_on:  # `ablate ... -- TRAIN_FLAGS`: the rest goes to train.py, with ReFlow's flags
            checks.append((tokens, help_request("script", "train.py", ["--plugin", "reflow"]), typed_flags(passed_on)))
    new = sorted({request for _, request, _ in checks} - set(_HELP_CACHE), key=repr)
    if new:  # one interpreter for every --help not asked before in this test run
        _HELP_CACHE.update(zip(new, help_texts([(k, t, list(a)) for k, t, a in new], root)))
    problems = []
    for tokens, request, flags in checks:
        result = _HELP_CACHE[request]
        command = " ".join(tokens)
        if result["code"] != 0:
            problems.append(f"{command}: --help exits {result['code']}: {result['output'][-300:]}")
        elif unknown := unlisted_flags(flags, result["output"]):
            problems.append(f"{command}: {request[1]} has no {', '.join(unknown)}")
    return problems


# ---------------------------------------------------------------------------- the checks


def test_no_diary_wording_in_tracked_text_files():
    offending = [f"{path.relative_to(ROOT)}:{line}: {words!r}"
                 for path in tracked_text_files(ROOT)
                 for line, words in diary_hits(path.read_text(encoding="utf-8"))]
    assert not offending, "diary wording (use a date or a commit instead):\n" + "\n".join(offending)


def test_links_and_named_paths_of_readme_and_docs_exist():
    folders = _top_level_folders(tracked_text_files(ROOT), ROOT)
    problems = []
    for page in _doc_pages(ROOT):
        text = page.read_text(encoding="utf-8")
        problems += [f"{page.relative_to(ROOT)}: link {link}" for link in dead_links(page, text)]
        problems += [f"{page.relative_to(ROOT)}: path {path}" for path in missing_paths(text, ROOT, folders)]
    assert not problems, "dead links or paths:\n" + "\n".join(problems)


def test_module_map_names_modules_that_exist():
    files = {path.relative_to(ROOT).as_posix() for path in tracked_text_files(ROOT)}
    gaps = module_map_gaps((ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8"), files)
    assert not gaps, "docs/ARCHITECTURE.md names modules that do not exist:\n" + "\n".join(gaps)


def test_readme_python_commands_parse():
    commands = python_commands((ROOT / "README.md").read_text(encoding="utf-8"))
    assert len(commands) >= 10, commands  # the README's commands are found at all
    problems = command_problems(commands, ROOT)
    assert not problems, "README commands that do not parse:\n" + "\n".join(problems)


# ---------------------------------------------------------------------------- the detectors


@pytest.mark.parametrize("line", [  # each in two pieces: the joined text is what is checked
    "measured at stop " "34, PSNR 24.92", "the defaults after this " "stop", "stop" "-32 clean-clone figures",
    "Latest (third GPU " "session)", "in the previous " "session", "the same code again, later " "session",
    "rendered with to" "day's defaults", "re-measured after this " "round's policy",
])
def test_diary_wording_is_found(line):
    assert diary_hits(f"intro\n{line}\n") and diary_hits(line)[0][0] == 1


@pytest.mark.parametrize("line", [
    "measured 2026-11-26 at commit 877daeb", "the transmittance stop (T < 1e-4)",
    "same order on ties, same stop", '@pytest.fixture(scope="session")', "computed once per session",
    "a camera that does not move stops here",
])
def test_ordinary_words_are_not_diary_wording(line):
    assert diary_hits(line) == []


def test_dead_links_and_paths_are_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "real.py").write_text("")
    (tmp_path / "docs" / "A.md").write_text("# Title\n\n## Some section (x)\n")
    page = tmp_path / "README.md"
    text = ("[ok](docs/A.md) [anchor](docs/A.md#some-section-x) ![img](docs/missing.png)\n"
            "[gone](docs/B.md) [bad anchor](docs/A.md#nowhere) [web](https://example.org/x)\n"
            "```\n[in code](docs/C.md)\n```\n"
            "see `baselines/real.py`, `baselines/gone.py` and docs/D.md, `baselines/{real,other}.py`,\n"
            "`877daeb:baselines/removed.py` (a file of that commit)\n")
    assert sorted(dead_links(page, text)) == [
        "docs/A.md#nowhere (no heading with that anchor)", "docs/B.md (no such file)",
        "docs/missing.png (no such file)"]
    assert missing_paths(text, tmp_path, {"baselines", "docs"}) == [
        "baselines/gone.py", "baselines/other.py", "docs/B.md", "docs/C.md", "docs/D.md", "docs/missing.png"]


def test_module_map_gaps_are_found():
    files = {"baselines/render/kernel.py", "baselines/fourdgs/interrupt.py", "reflow_plugin/flow.py"}
    text = ("# Map\n\n## `baselines/render`: raster\n`kernel.py`, `gone.py`, `fourdgs/interrupt.py`, `reflow_plugin/flow.py`\n"
            "## Shared conventions\n`anything.py`\n## `reflow_plugin`: ReFlow\n`flow.py` and `plugin.py`\n")
    assert module_map_gaps(text, files) == ["gone.py (section of baselines/)", "plugin.py (section of reflow_plugin/)"]


def test_readme_commands_are_extracted():
    markdown = ("text\n\n    python train.py -s data/x --plugin reflow   # a comment\n"
                "    OMP_NUM_THREADS=1 python -m baselines.prepare clip.mp4 -o out \\\n        --size 320\n"
                "    bash benchmarks/gpu_check.sh\n\nnot code: python train.py --nope\n"
                "```\npython3 scripts/with_venv.py -m pytest -q\n```\n")
    commands = python_commands(markdown)
    assert commands == [["python", "train.py", "-s", "data/x", "--plugin", "reflow"],
                        ["python", "-m", "baselines.prepare", "clip.mp4", "-o", "out", "--size", "320"],
                        ["python3", "scripts/with_venv.py", "-m", "pytest", "-q"]]
    assert command_target(commands[2]) == ("module", "pytest", ["-q"])
    assert typed_flags(["-s", "x", "--mask_offsets", "-4", "2", "--a=1", "--"]) == ["-s", "--mask_offsets", "--a"]


def test_a_flag_help_does_not_list_is_found():
    commands = [["python", "-m", "baselines.prepare", "x", "-o", "y", "--size", "320", "--no_such_flag"],
                ["python", "train.py", "--plugin", "reflow", "--lambda_ff", "1", "--not_a_reflow_flag"],
                ["python", "-m", "no_such_module_here"]]
    problems = command_problems(commands, ROOT)
    assert len(problems) == 3, problems
    assert problems[0].endswith("baselines.prepare has no --no_such_flag")  # --size and -o are listed
    assert problems[1].endswith("train.py has no --not_a_reflow_flag")     # --lambda_ff is ReFlow's
    assert "--help exits 1" in problems[2]
