"""Every `--help` line true (issue 48): every command's and subcommand's help is run and read back.

(a) a setting's choices are its Literal (stages' Settings, the fit's, calib's, synth's), and where
    the prose lists values, they are the code's (fit --brdf's models, export --out's formats,
    synth --env's procedural maps); (b) a default is said at most once per option, and as a value
    ("(default: True)", "None", an empty value never); (c) a flag is worded as a flag: --no-report
    says what it does, a --name / --no-name pair names its default flag; and no subcommand repeats
    the global -v.  The help comes from one place (pipeline.settings.HelpFormatter,
    add_settings_arguments; pipeline.cli's parsers), so these hold for every command at once.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import io
import re
import typing
import warnings

import pytest

from pipeline import STAGES, cli

EXPECTED = {
    "",
    *STAGES,
    "export",
    "run",
    "batch",
    "calib",
    "calib intrinsics",
    "calib response",
    "calib vignetting",
    "synth",
    "env",
    "env project",
    "env render",
    "env irradiance",
    "env make",
    "planar",
    "planar figures",
    "bench",
}


def parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command words, parser) of the command line and every subcommand under it."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from parsers(sub, (*path, name))


def choices_of(cls, name: str) -> tuple:
    """The values of a Literal-typed field, else ()."""
    tp = typing.get_type_hints(cls)[name]
    return typing.get_args(tp) if typing.get_origin(tp) is typing.Literal else ()


def settings_class(path: tuple[str, ...]):
    """The settings dataclass a command's options come from, or None."""
    if len(path) == 1 and path[0] in (*STAGES, "export"):
        return importlib.import_module(f"stages.{path[0]}").Settings
    if len(path) == 2 and path[0] == "calib":
        return importlib.import_module(f"calib.{path[1]}").Settings
    if path == ("synth",):
        return importlib.import_module("pipeline.synth").SynthSettings
    if path == ("env", "make"):
        return importlib.import_module("pipeline.commands.env").MakeSettings
    return None


@pytest.fixture(scope="module")
def helps():
    """{command words: (parser, its --help text)}, each text printed by `sigrend ... --help`, wide
    enough that no option's help is wrapped within a word."""
    found = {" ".join(path): (path, parser) for path, parser in parsers(cli.build_parser())}
    assert EXPECTED <= set(found), sorted(EXPECTED - set(found))
    out = {}
    mp = pytest.MonkeyPatch()
    mp.setenv("COLUMNS", "400")
    try:
        for name, (path, parser) in found.items():
            buffer = io.StringIO()
            with contextlib.redirect_stdout(buffer), pytest.raises(SystemExit) as done:
                cli.main([*path, "--help"])
            assert done.value.code == 0, name
            out[name] = (path, parser, buffer.getvalue())
    finally:
        mp.undo()
    return out


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def option_help(parser: argparse.ArgumentParser, text: str, action: argparse.Action) -> str:
    """The lines of ``text`` that describe ``action`` (its invocation, then its help), joined."""
    invocation = parser._get_formatter()._format_action_invocation(action)
    lines = text.splitlines()
    start = next(
        i
        for i, line in enumerate(lines)
        if _indent(line) == 2 and (line.strip() == invocation or line.strip().startswith(invocation + " "))
    )
    block = [lines[start]]
    for line in lines[start + 1 :]:
        if _indent(line) <= 2:
            break
        block.append(line)
    return " ".join(" ".join(block).split())


def shown_actions(parser: argparse.ArgumentParser):
    return [
        a
        for a in parser._actions
        if a.help != argparse.SUPPRESS and a.option_strings and not isinstance(a, (argparse._HelpAction, argparse._VersionAction))
    ]


def test_every_command_has_a_help(helps):
    """Every command and subcommand has a --help starting 'usage: sigrend'."""
    for name, (_, _, text) in helps.items():
        assert text.startswith("usage: sigrend"), name


def test_a_default_is_said_once_and_as_a_value(helps):
    """(b): no "(default: X) (default: Y)" (e.g. -w's "<capture>-work" and argparse's "None"), no
    default that is not a value a user could type."""
    for name, (_, parser, text) in helps.items():
        for action in shown_actions(parser):
            line = option_help(parser, text, action)
            assert line.count("(default:") <= 1, (name, line)
            assert not re.search(r"\(default: *(True|False|None|\[\]|\(\)|''|)\)", line), (name, line)


def test_flags_are_worded_as_flags(helps):
    """(c): --no-report / --force / --no-shadows say what they do (no "(default: True)", which reads
    as "no report by default"); a --name / --no-name setting names its default flag."""
    for name, (path, parser, text) in helps.items():
        cls = settings_class(path)
        for action in shown_actions(parser):
            line = option_help(parser, text, action)
            if isinstance(action, argparse.BooleanOptionalAction):
                assert cls is not None, (name, line)
                field = next(f for f in dataclasses.fields(cls) if f.name == action.dest)
                flag = action.option_strings[0] if field.default else "--no-" + action.option_strings[0][2:]
                assert line.endswith(f"(default: {flag})"), (name, line)
            elif action.nargs == 0:
                assert "(default:" not in line, (name, line)


def test_the_global_verbose_is_the_only_one(helps):
    """`sigrend -v` serves every command; poses' old --verbose still works, hidden, with a warning."""
    for name, (path, _parser, text) in helps.items():
        if path:
            assert "--verbose" not in text, name
    for argv in (["-v", "poses", "CAP"], ["poses", "CAP", "--verbose"]):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            args = cli.build_parser("poses").parse_args(argv)
        settings = importlib.import_module("pipeline.settings").settings_from_args(
            importlib.import_module("stages.poses").Settings, args
        )
        assert settings.verbose and args.verbose, argv
        deprecated = [w for w in caught if "deprecated" in str(w.message)]
        assert len(deprecated) == (argv[0] == "poses"), argv


def test_choices_are_the_literals(helps):
    """(a): every setting whose type is a Literal offers exactly its values, in the help's {...},
    and prose that lists two or more of them lists them all."""
    checked = 0
    for name, (path, parser, text) in helps.items():
        cls = settings_class(path)
        if cls is None:
            continue
        by_dest = {a.dest: a for a in shown_actions(parser)}
        for field in dataclasses.fields(cls):
            values = choices_of(cls, field.name)
            if not values or field.metadata.get("cli") is False:
                continue
            action = by_dest[field.name]
            assert tuple(action.choices) == values, (name, field.name)
            line = option_help(parser, text, action)
            assert "{" + ",".join(map(str, values)) + "}" in line, (name, line)
            prose = field.metadata["help"]
            named = [v for v in values if re.search(rf"(?<![\w-]){re.escape(str(v))}(?![\w-])", prose)]
            assert len(named) < 2 or len(named) == len(values), (name, field.name, named)
            checked += 1
    assert checked >= 15


def test_defaults_are_the_settings_defaults(helps):
    """The default each setting's help states is its field's default, as a user types it."""
    for name, (path, parser, text) in helps.items():
        cls = settings_class(path)
        if cls is None:
            continue
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for action in shown_actions(parser):
            field = fields.get(action.dest)
            if field is None or action.nargs == 0 or field.metadata.get("cli") is False:
                continue
            default = field.default if field.default is not dataclasses.MISSING else field.default_factory()
            line = option_help(parser, text, action)
            if default in ("", (), [], None) or "(default:" in field.metadata.get("help", ""):
                continue
            if isinstance(default, tuple):
                default = ("x" if action.metavar == "WxH" else "," if action.metavar == "MIN,MAX" else " ").join(
                    map(str, default)
                )
            assert line.endswith(f"(default: {default})"), (name, line)


def _listed(line: str, pattern: str) -> set[str]:
    match = re.search(pattern, line)
    assert match, (pattern, line)
    return {w for w in re.split(r",\s*|\s+and\s+|\s+or\s+", match.group(1)) if w}


def test_prose_lists_are_the_codes(helps):
    """The values a help names in prose are the code's: fit --brdf's models and what 'auto' chooses
    among on each path, export --out's formats, the procedural maps of synth --env, relight --env and env make."""
    from pipeline.core.brdf import BRDF_PARAMS, LOBE_MODELS
    from pipeline.core.procedural_envmaps import ENV_PARAMS
    from stages.export import WRITERS

    def line_of(command: str, dest: str) -> str:
        _, parser, text = helps[command]
        return option_help(parser, text, next(a for a in parser._actions if a.dest == dest and a.help != argparse.SUPPRESS))

    brdf = line_of("fit", "brdf")
    assert _listed(brdf, r"a model name \(([^)]*)\)") == set(BRDF_PARAMS)
    assert _listed(brdf, r"--forward physical\) among ([\w ,]+?) \(") == {"lambert", "principled"}
    assert "a metal" in brdf
    assert _listed(brdf, r"--forward convex\) among ([\w ,]+?);") == {"lambert", *LOBE_MODELS}
    out = line_of("export", "out")
    assert set(re.findall(r"(?<!\S)(\.\w+)", out.split("empty")[0])) == set(WRITERS)
    for command, dest in (("synth", "env"), ("relight", "env"), ("env make", "spec")):  # one list: spec_help
        env = line_of(command, dest)
        assert _listed(env, r"NAME one of ([^(]*) \(") == set(ENV_PARAMS), command
