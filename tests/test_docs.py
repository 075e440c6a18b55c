"""The documentation (issue 29): `README.md` is the front door, `docs/` holds a page per topic.

Checked here, for `README.md`, every page `docs/*.md` and every `docs/**/README.md`:

1. every relative link and image resolves to an existing file or folder (`#anchors` and `?queries` are
   stripped; http(s), mailto and same-page `#anchor` links are not checked); every broken one is reported
   with its file and target;
2. every page `docs/*.md` is linked from `README.md`, directly or through the index `docs/README.md`;
3. every command in a fenced `bash` / `sh` / unlabelled code block that runs `condground <cmd>` names a
   command of `lerobot_condground.cli.COMMANDS`, and every `--flag` it passes (the part before `=`; a
   dotted flag by its full dotted name) appears in `condground <cmd> --help`; the same for LeRobot's stock
   console scripts shown (`lerobot-train`, `lerobot-eval`, `lerobot-record`, `lerobot-dataset-viz`,
   `lerobot-rollout`, ...) against their own `--help`. Continued lines (`\\` at the end) are joined, a
   line may hold several commands (`;`, `&&`, `|`), and lines starting with `#` are skipped.

Two exceptions to "appears in --help". First, LeRobot's choice groups: `--policy`, `--env`, `--robot`,
`--teleop`, `--strategy`, ... are draccus choice registries: which fields they have depends on the type
chosen on the command line (`--policy.type=act_modified`, or the type in the checkpoint `--policy.path`
names), so `--help` lists only the group and its `.type` (`--policy`, `--policy.type`), never a type's
own fields (`--policy.variant`, `--policy.dropout`, `--robot.host`). A dotted flag missing from `--help`
is therefore accepted when its nearest ancestor group listed in `--help` is such a choice group (its
`--<group>.type` is listed too): the command hands that group to LeRobot's parser, which checks the
field against the chosen type when the command runs. A field of a group that is not a choice group
(`--dataset.*` of `lerobot-train`, `--eval.*`) must appear itself. Second, the flag groups a command takes
out of its arguments before draccus parses (and documents) the rest, listed in `PARSED_BEFORE_DRACCUS`.

The `--help` texts are collected in one subprocess for the whole run: it calls each console script's
entry point (the function `.venv/bin/<script>` runs, read from the installed entry points) with
`<script> [<cmd>] --help` as its `sys.argv`, so each text is what the console script prints, while the
import of LeRobot (about 7 s on the 2-core machine) is paid once rather than once per command.
"""

import json
import re
import shlex
import sys
from functools import cache
from pathlib import Path
from urllib.parse import unquote

from markdown_it import MarkdownIt

from helpers import run_cli

ROOT = Path(__file__).resolve().parents[1]
SHELL_FENCES = {"", "bash", "sh", "shell"}
SEPARATORS = {";", "&", "&&", "|", "||"}
FLAG = re.compile(r"--[A-Za-z_][\w.-]*")
# Flag groups a command takes out of its arguments before draccus parses (and documents) the rest, so its
# `--help` cannot list them: `condground pi05-start` documents `--policy.path` and hands every other
# `--policy.*` to pi05_grounded's configuration (`lerobot_condground/scripts/pi05_start.py`, `parse`).
PARSED_BEFORE_DRACCUS = {"condground:pi05-start": ("--policy.",)}

# Runs in the subprocess: argv[1] is the JSON file to write, the rest `script` or `script:command` names.
HELP_BATCH = r"""
import contextlib, io, json, sys, time, traceback
from importlib.metadata import entry_points

scripts = {ep.name: ep for ep in entry_points(group="console_scripts")}
out, texts = sys.argv[1], {}
for name in sys.argv[2:]:
    script, _, command = name.partition(":")
    buffer, started = io.StringIO(), time.monotonic()
    sys.argv = [script, *([command] if command else []), "--help"]
    error = None
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(buffer):
        try:
            if script not in scripts:
                raise LookupError(f"no console script {script!r} is installed")
            code = scripts[script].load()()  # what the console script passes to sys.exit
            if code not in (0, None):
                error = f"exit code {code}"
        except SystemExit as stop:
            if stop.code not in (0, None):
                error = f"exit code {stop.code}"
        except BaseException:
            error = traceback.format_exc()
    texts[name] = {"text": buffer.getvalue(), "error": error, "seconds": time.monotonic() - started}
with open(out, "w") as file:
    json.dump(texts, file)
"""


def markdown_files() -> list[Path]:
    """README.md, the pages directly under docs/, and the README.md of every folder below docs/."""
    docs = ROOT / "docs"
    return [ROOT / "README.md", *sorted(docs.glob("*.md")), *sorted(docs.glob("*/**/README.md"))]


@cache
def tokens(path: Path) -> list:
    return MarkdownIt("commonmark").enable("table").parse(path.read_text(encoding="utf-8"))


def links(path: Path) -> list[str]:
    """Every link and image target of a Markdown file (code spans and code blocks hold none)."""
    found = []
    for block in tokens(path):
        for token in block.children or ():
            if token.type == "link_open":
                found.append(token.attrGet("href"))
            elif token.type == "image":
                found.append(token.attrGet("src"))
    return found


def local_target(path: Path, target: str) -> Path | None:
    """The file or folder a relative link points at; None for external and same-page links."""
    if re.match(r"[A-Za-z][\w+.-]*:", target) or target.startswith(("#", "//")):
        return None
    target = unquote(target.split("#", 1)[0].split("?", 1)[0])
    return (ROOT / target.lstrip("/")) if target.startswith("/") else (path.parent / target)


def broken_links(paths: list[Path]) -> list[str]:
    broken = []
    for path in paths:
        for target in links(path):
            resolved = local_target(path, target)
            if resolved is not None and not resolved.exists():
                broken.append(f"{path.relative_to(ROOT)}: {target}")
    return broken


def linked_files(path: Path) -> set[Path]:
    return {
        resolved.resolve()
        for target in links(path)
        if (resolved := local_target(path, target)) is not None and resolved.exists()
    }


def shell_blocks(path: Path) -> list[str]:
    return [
        token.content
        for token in tokens(path)
        if token.type == "fence" and (token.info.split() or [""])[0] in SHELL_FENCES
    ]


def logical_lines(code: str) -> list[str]:
    """The block's lines with continuations (a trailing backslash) joined and comment lines dropped."""
    lines, pending = [], ""
    for raw in code.splitlines():
        line = raw.rstrip()
        if not pending and line.lstrip().startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        lines.append(pending + line)
        pending = ""
    return [*lines, pending] if pending.strip() else lines


def split_words(line: str) -> list[str]:
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
    lexer.whitespace_split = True
    try:
        return list(lexer)
    except ValueError:  # an unbalanced quote: fall back to whitespace
        return line.split()


def commands(code: str) -> list[tuple[str, str | None, list[str]]]:
    """(script, condground command or None, flags) for every condground or stock lerobot-* call."""
    found = []
    for line in logical_lines(code):
        segment: list[str] = []
        for word in [*split_words(line), ";"]:
            if word not in SEPARATORS:
                segment.append(word)
                continue
            for i, word_i in enumerate(segment):
                script = Path(word_i).name
                if script == "condground" or script.startswith("lerobot-"):
                    args = segment[i + 1 :]
                    command = args[0] if script == "condground" and args and args[0][:1] != "-" else None
                    flags = [arg.strip("[]").split("=", 1)[0] for arg in args]
                    found.append((script, command, [f for f in flags if FLAG.fullmatch(f)]))
                    break
            segment = []
    return found


def flag_known(flag: str, listed: set[str]) -> bool:
    """In `--help`, or a field of a LeRobot choice group listed there (see the module's docstring)."""
    if flag in listed:
        return True
    parts = flag[2:].split(".")
    for end in range(len(parts) - 1, 0, -1):
        group = "--" + ".".join(parts[:end])
        if group in listed:
            return f"{group}.type" in listed
    return False


@cache
def help_texts(names: tuple[str, ...]) -> dict[str, dict]:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "help.json"
        run_cli("python", "-c", HELP_BATCH, str(out), *names, timeout=300)
        return json.loads(out.read_text())


def shown_commands() -> list[tuple[Path, str, str | None, list[str]]]:
    return [
        (path, script, command, flags)
        for path in markdown_files()
        for block in shell_blocks(path)
        for script, command, flags in commands(block)
    ]


def test_links_and_images_resolve():
    broken = broken_links(markdown_files())
    assert not broken, "broken relative links or images:\n" + "\n".join(broken)


def test_every_docs_page_is_linked_from_the_readme():
    reachable = linked_files(ROOT / "README.md")
    index = (ROOT / "docs" / "README.md").resolve()
    if index in reachable:
        reachable |= linked_files(index)
    pages = sorted((ROOT / "docs").glob("*.md"))
    missing = [str(page.relative_to(ROOT)) for page in pages if page.resolve() not in reachable]
    assert pages, "no page under docs/"
    assert not missing, f"pages not linked from README.md or docs/README.md: {missing}"


def test_commands_and_flags_shown_exist():
    from lerobot_condground.cli import COMMANDS

    shown = shown_commands()
    assert any(script == "condground" for _, script, _, _ in shown), "no condground command found"
    problems = [
        f"{path.relative_to(ROOT)}: `condground {command}` is no command; allowed: {', '.join(COMMANDS)}"
        for path, script, command, _ in shown
        if script == "condground" and command is not None and command not in COMMANDS
    ]
    names = {
        f"{script}:{command}" if script == "condground" else script
        for _, script, command, _ in shown
        if script != "condground" or command in COMMANDS
    }
    texts = help_texts(tuple(sorted(names)))
    for path, script, command, flags in shown:
        name = f"{script}:{command}" if script == "condground" else script
        if name not in texts:
            continue
        entry = texts[name]
        if entry["error"]:
            problems.append(f"`{name.replace(':', ' ')} --help` failed: {entry['error'][-2000:]}")
            continue
        listed = set(FLAG.findall(entry["text"]))
        problems += [
            f"{path.relative_to(ROOT)}: `{name.replace(':', ' ')}` has no flag {flag}"
            for flag in flags
            if not flag_known(flag, listed) and not flag.startswith(PARSED_BEFORE_DRACCUS.get(name, ()))
        ]
    timings = ", ".join(f"{name} {entry['seconds']:.1f} s" for name, entry in sorted(texts.items()))
    print(f"--help collected: {timings}", file=sys.stderr)
    assert not problems, "\n".join(sorted(set(problems)))


def test_the_checks_catch_mistakes(tmp_path, monkeypatch):
    """The checkers above can fail: a broken link and image are reported, commands and flags are read
    through continuations, comments, brackets and several commands on a line."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "there.md").write_text("x")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](there.md#part) [gone](missing.md) ![pic](img/none.png) [web](https://example.com) "
        "`[code](not/a/link.md)`\n\n```bash\n# condground record --not.checked=1\n"
        "condground record --env.task=X \\\n  --dataset.root=d [--seed=3]  # --comment\n"
        "hf download x && lerobot-eval --policy.path=p; condground nosuch --a.b=1\n```\n"
    )
    assert broken_links([page]) == ["page.md: missing.md", "page.md: img/none.png"]
    assert commands(shell_blocks(page)[0]) == [
        ("condground", "record", ["--env.task", "--dataset.root", "--seed"]),
        ("lerobot-eval", None, ["--policy.path"]),
        ("condground", "nosuch", ["--a.b"]),
    ]
    listed = {"--policy", "--policy.type", "--dataset", "--dataset.root"}
    assert flag_known("--policy.variant", listed) and flag_known("--dataset.root", listed)
    assert not flag_known("--dataset.rooot", listed) and not flag_known("--steps", listed)
