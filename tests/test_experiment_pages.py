"""Each experiment page's "How to run" commands work as written, in their short form.

The commands are read from the page's fenced bash blocks under ``## How to run`` (shell variables
and continuation lines resolved as the shell would), then each is run in a form that takes seconds:

* ``pdem DECK [--set …]`` (serial or under ``mpirun``): ``pdem check --deck-only`` with the same
  deck and overrides — the deck and every override are valid;
* ``pdem study SPEC [options]``: the same with ``--dry-run`` — the spec and its grid resolve;
* ``python tools/X.py [options]``: the tool exists and every option it is given is one it has;
* ``pdem check|advise DECK [--set …]``: as ``pdem DECK``;
* ``pdem resume CHECKPOINT --set …``: the overrides are ``KEY=VALUE``.

With ``--runslow``, every ``pdem DECK`` command also runs for a few steps into a scratch folder.
"""

from __future__ import annotations

import contextlib
import io
import re
import runpy
import shlex
import sys
from pathlib import Path

import pytest

from pdem.cli import main as pdem_main

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs" / "experiments").glob("*.md"))


def how_to_run(page: Path) -> list[list[str]]:
    """The commands of a page's ``## How to run`` section, as argument lists."""
    text = page.read_text()
    m = re.search(r"^## How to run\n(.*?)(?=^## )", text, re.S | re.M)
    assert m, f"{page.name}: no '## How to run' section"
    commands: list[list[str]] = []
    env: dict[str, str] = {}
    for block in re.findall(r"```bash\n(.*?)```", m.group(1), re.S):
        lines: list[str] = []
        loop: tuple[str, list[str], list[str]] | None = None  # variable, values, body
        for line in block.replace("\\\n", " ").splitlines():
            head = re.fullmatch(r"\s*for (\w+) in ([^;]*); do\s*", line)
            if head:
                loop = (head.group(1), head.group(2).split(), [])
            elif loop is not None and line.strip() == "done":
                var, values, body = loop
                lines += [b.replace("$" + var, v) for v in values for b in body]
                loop = None
            elif loop is not None:
                loop[2].append(line)
            else:
                lines.append(line)
        for line in lines:
            tokens = shlex.split(line, comments=True)
            if not tokens:
                continue
            if len(tokens) == 1 and re.fullmatch(r"[A-Z_]+=.*", tokens[0]):
                name, _, value = tokens[0].partition("=")
                env[name] = value
                continue
            expanded: list[str] = []
            for tok in tokens:
                if re.fullmatch(r"\$[A-Z_]+", tok):
                    expanded += shlex.split(env[tok[1:]])
                else:
                    expanded.append(tok)
            command: list[str] = []
            for tok in expanded + ["&&"]:
                if tok == "&&":
                    if command:
                        commands.append(command)
                    command = []
                else:
                    command.append(tok)
    return commands


def _strip_launcher(cmd: list[str]) -> list[str]:
    if cmd and cmd[0] in ("mpirun", "mpiexec"):
        cmd = cmd[1:]
        while cmd and cmd[0].startswith("-"):
            cmd = cmd[2:] if cmd[0] in ("-n", "-np") else cmd[1:]
    return cmd


def _sets(args: list[str]) -> list[str]:
    out = []
    for k, a in enumerate(args):
        if a == "--set":
            out += ["--set", args[k + 1]]
    return out


def _pdem(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = pdem_main(argv)
    return code, err.getvalue()


def _tool_options(script: Path, *sub: str) -> str:
    out = io.StringIO()
    argv = sys.argv
    sys.argv = [str(script), *sub, "--help"]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            with pytest.raises(SystemExit) as exit_:
                runpy.run_path(str(script), run_name="__main__")
    finally:
        sys.argv = argv
    assert exit_.value.code in (0, None), f"{script.name} --help exited {exit_.value.code}"
    return out.getvalue()


def _cases():
    for page in PAGES:
        for k, cmd in enumerate(how_to_run(page)):
            yield pytest.param(page, cmd, id=f"{page.stem}-{k}-{' '.join(cmd)[:60]}")


def test_every_experiment_page_has_commands():
    assert len(PAGES) >= 4
    for page in PAGES:
        cmds = [_strip_launcher(c) for c in how_to_run(page)]
        assert any(c and c[0] == "pdem" for c in cmds), f"{page.name}: no pdem command"


def test_the_command_reader_resolves_variables_and_continuations(tmp_path):
    page = tmp_path / "p.md"
    page.write_text(
        "## How to run\n\n```bash\nR=\"--set a.b=1 --set c.d=2\"\n"
        "mpirun -n 2 pdem x.toml $R \\\n   --output o   # comment\npdem y.toml && python tools/t.py --z\n"
        'for v in 1 2; do\n  pdem z.toml --set "a.v=[$v, 0]"\ndone\n```\n\n## Next\n'
    )
    cmds = how_to_run(page)
    assert cmds == [
        ["mpirun", "-n", "2", "pdem", "x.toml", "--set", "a.b=1", "--set", "c.d=2", "--output", "o"],
        ["pdem", "y.toml"],
        ["python", "tools/t.py", "--z"],
        ["pdem", "z.toml", "--set", "a.v=[1, 0]"],
        ["pdem", "z.toml", "--set", "a.v=[2, 0]"],
    ]


@pytest.mark.parametrize("page, cmd", list(_cases()))
def test_page_command_in_short_form(page, cmd, tmp_path, monkeypatch, request):
    monkeypatch.chdir(ROOT)
    cmd = _strip_launcher(cmd)
    assert cmd, f"{page.name}: empty command"
    where = f"{page.name}: `{' '.join(cmd)}`"
    if cmd[0] == "python":
        script = ROOT / cmd[1]
        assert script.is_file(), f"{where}: no such tool"
        helptext = _tool_options(script)
        sub = cmd[2] if len(cmd) > 2 else ""
        if re.search(r"\{[\w,-]*\b" + re.escape(sub) + r"\b[\w,-]*\}", helptext):
            helptext = _tool_options(script, sub)  # a subcommand's own options
        for opt in (a.split("=")[0] for a in cmd[2:] if a.startswith("--")):
            assert opt in helptext, f"{where}: {script.name} has no option {opt}"
        return
    assert cmd[0] == "pdem", f"{where}: not a pdem, mpirun or python command"
    args = cmd[1:]
    if args[0] == "study":
        spec = ROOT / args[1]
        assert spec.is_file(), f"{where}: no such spec"
        opts = [a for a in args[2:] if a not in ("--output",)]
        code, err = _pdem(["study", args[1], *opts, "--dry-run", "--output", str(tmp_path / "study")])
        assert code == 0, f"{where}: {err}"
        return
    if args[0] == "resume":
        # the checkpoint is a finished run's; the overridden keys must be deck keys of some deck
        assert all(s.count("=") >= 1 for s in _sets(args)[1::2]), where
        return
    if args[0] in ("check", "advise"):
        args = args[1:]
    deck = args[0]
    assert (ROOT / deck).is_file(), f"{where}: no such deck"
    code, err = _pdem(["check", "--deck-only", deck, *_sets(args)])
    assert code == 0, f"{where}: {err}"
    if request.config.getoption("--runslow"):
        code, err = _pdem([deck, *_sets(args), "--steps", "5", "--quiet", "--output", str(tmp_path / "run")])
        assert code == 0, f"{where}: {err}"


def test_the_short_form_catches_a_wrong_key_and_a_wrong_option(monkeypatch):
    """Not vacuous: a misspelt override and an option a tool lacks are caught."""
    monkeypatch.chdir(ROOT)
    code, err = _pdem(["check", "--deck-only", "inputs/hopper.toml", "--set", "run.dtt=1e-5"])
    assert code == 2 and "run.dtt" in err
    assert "--no-such-option" not in _tool_options(ROOT / "tools" / "render.py")
