"""Every option reachable from the API, the CLI and the plugin with one default; no import cycle."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
from pathlib import Path

import pytest

import mirad
from mirad import options
from mirad.cli import command_options
from mirad.integrator import make_integrator
from mirad.settings import Settings

PACKAGE = Path(mirad.__file__).parent


def _cli_actions(command):
    return command_options(command)


def test_every_settings_field_is_an_option_with_the_dataclass_default():
    fields = {f.name: f.default for f in dataclasses.fields(Settings)}
    assert [o.name for o in options.SOLVE] == list(fields)
    for o in options.SOLVE:
        assert o.default == fields[o.name]
        assert o.help, f"Settings docstring documents no {o.name}"


def test_settings_docstring_states_the_field_defaults():
    """The docstring's 'name : type, default X' is what the dataclass holds (documented once, right)."""
    for name, shown in re.findall(r"\n    (\w+) : [^\n]*?default ([^\n]+)", Settings.__doc__):
        actual = getattr(Settings, name)
        try:
            documented = ast.literal_eval(shown.strip())
        except ValueError:
            documented = {"False": False, "True": True, "None": None}.get(shown.strip(), shown.strip())
        assert documented == actual, f"Settings.{name}: docstring says {shown.strip()}, the field holds {actual!r}"


@pytest.mark.parametrize("command", ["solve", "render", "export", "probe"])
def test_cli_commands_take_every_solver_option_unset_by_default(command):
    actions = _cli_actions(command)
    for o in options.SOLVE:
        assert o.name in actions, f"mirad {command} lacks {o.flag}"
        if o.name != "quiet":
            assert actions[o.name].default is None          # unset: Settings decides, not the CLI
        if o.choices:
            assert tuple(actions[o.name].choices) == o.choices


def test_cli_help_shows_the_settings_default():
    actions = _cli_actions("solve")
    assert "(default 0.03)" in actions["tolerance"].help
    assert "(default kernel)" in actions["oracle"].help
    for o in options.RENDER:
        assert o.name in _cli_actions("render")


def test_api_repeats_no_default():
    """mirad.solve takes Settings' fields as **options; render's display defaults are RENDER's."""
    params = inspect.signature(mirad.solve).parameters
    assert set(params) == {"scene", "quiet", "options"}
    render = inspect.signature(mirad.render).parameters
    for o in options.RENDER:
        assert render[o.name].default == o.default
    with pytest.raises(mirad.SettingsError, match="tolerence"):
        mirad.solve("scenes/cornell-box/scene.xml", tolerence=0.1)


def test_plugin_reads_every_option_but_the_variant():
    changed = {"tolerance": 0.2, "samples_per_link": 8, "seed": 3, "solver": "jacobi", "oracle": "bf",
               "clustering": "off", "max_links": 1000, "shadow_textures": True, "core": "legacy",
               "final_gather": True, "gather_rays": 2, "smooth": False, "min_area_factor": 0.1}
    integrator = make_integrator(**changed)
    for name, value in changed.items():
        assert getattr(integrator, name) == value
    names = {o.name for o in options.PLUGIN}
    assert names == {o.name for o in options.SOLVE} - {"variant"} | {o.name for o in options.RENDER} - {"spp"}
    for o in options.PLUGIN:
        assert f" * - {o.name}\n" in type(integrator).__doc__
    with pytest.raises(mirad.SettingsError, match="tolerance"):
        make_integrator(tolerance=2.0)
    with pytest.raises(mirad.SettingsError, match="gather_rays"):
        make_integrator(gather_rays=0)


def _imports(path: Path) -> set:
    """mirad modules a module imports anywhere in its body (function-local imports included)."""
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.level == 1 or (node.module or "").startswith("mirad")):
            parts = (node.module or "").split(".")
            sub = parts[0] if node.level == 1 else (parts[1] if len(parts) > 1 else "")
            if sub:
                out.add(sub)
            else:
                out |= {a.name if a.name in modules else "__init__" for a in node.names}
    return out & (modules | {"__init__"})


def test_mirad_has_no_import_cycle():
    """Every import, function-local ones included, points one way (cli, the top, excepted from
    nothing: it imports the package, nothing imports it)."""
    graph = {p.stem: _imports(p) for p in PACKAGE.glob("*.py")}
    state = {}

    def visit(node, path):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                raise AssertionError("import cycle: " + " -> ".join(path + [nxt]))
            if nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])


@pytest.mark.parametrize("options, words", [
    ({"tolerance": "0.1"}, ["tolerance='0.1'", "must be a number"]),
    ({"tolerance": float("nan")}, ["tolerance=nan", "finite"]),
    ({"quiet": "false"}, ["quiet='false'", "True or False"]),
    ({"max_links": 2.5}, ["max_links=2.5", "integer"]),
])
def test_type_checks_hold_when_the_annotations_are_evaluated(options, words, monkeypatch):
    """Settings' field annotations are strings here (``from __future__ import annotations``); a
    tool that evaluates them leaves the types themselves in ``dataclasses.fields`` (seen on a GPU
    machine's Python 3.12 test run, where these settings then passed unchecked)."""
    import typing

    from mirad import options as options_module

    hints = typing.get_type_hints(Settings)
    for field in dataclasses.fields(Settings):
        monkeypatch.setattr(field, "type", hints[field.name])
    assert not isinstance(dataclasses.fields(Settings)[0].type, str)
    with pytest.raises(mirad.SettingsError) as caught:
        Settings(**options)
    assert all(word in str(caught.value) for word in words)
    # the CLI's and plugin's option table reads the same annotations
    assert [(o.name, o.kind, o.optional) for o in options_module.settings_options()] == \
        [(o.name, o.kind, o.optional) for o in options_module.SOLVE]
