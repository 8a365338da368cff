"""The plugin system: entry-point discovery, registries, attribution, failures and environment."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

import pstoolkit
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.plugin import manager as plugins
from pstoolkit.plugin import spec as hookspecs
from pstoolkit.plugin.manager import PluginInfo, get_registries, load_failures, loaded_plugins
from pstoolkit.plugin.options import Option
from pstoolkit.plugin.registry import PluginError, Registry
from pstoolkit.testing import fake_distribution


def install(monkeypatch: pytest.MonkeyPatch, root: Path, sources: dict[str, str], version: str = "1.0") -> None:
    """Each plugin ``name`` as its own distribution ``pskfake-<name>`` with module ``pskfake_<name>``,
    on sys.path and allow-listed (so the real plugins stay out of the way)."""
    for name, source in sources.items():
        fake_distribution(root, f"pskfake-{name}", version, {name: f"pskfake_{name}"}, {f"pskfake_{name}": source})
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setenv(plugins.ALLOW_ENV, ",".join(sources))


@pytest.fixture
def fresh(pstoolkit_plugins_alone: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    """``pstoolkit.testing``'s isolated plugin state with pstoolkit's own plugins loaded only when
    named like a third party's, so a test sees just the plugins it installs."""
    return pstoolkit_plugins_alone


def solver_plugin(solver: str, *, option: bool = False) -> str:
    opts = '(Option("level", float, 0.5, "a level", minimum=0.0),)' if option else "()"
    return f"""
        from pstoolkit import Option, Solver, hookimpl

        class Thing(Solver):
            name = {solver!r}
            summary = "registers {solver}"
            options = {opts}

        @hookimpl
        def pstoolkit_register_solvers(registry):
            registry.register(Thing)
        """


ALL_HOOKS = """
    from pstoolkit import BRDF, Converter, LightBackend, LightCalibration, LightModel, ShadowDetector, Solver, hookimpl
    from pstoolkit.sim.renderers import SceneRenderer
    from pstoolkit.sim.scenes import Scene
    from pstoolkit.surface import Integrator

    __version__ = "9.9"

    @hookimpl
    def pstoolkit_register_light_models(registry):
        registry.register(LightModel, name="fake-light", summary="a light model")

    @hookimpl
    def pstoolkit_register_shadow_detectors(registry):
        registry.register(ShadowDetector, name="fake-shadow", summary="a shadow detector")

    @hookimpl
    def pstoolkit_register_brdfs(registry):
        registry.register(BRDF, name="fake-brdf", summary="a BRDF")

    @hookimpl
    def pstoolkit_register_solvers(registry):
        registry.register(Solver, name="fake-solver", summary="a solver")

    @hookimpl
    def pstoolkit_register_backends(registry):
        registry.register(LightBackend, name="fake-backend", summary="a backend")

    @hookimpl
    def pstoolkit_register_converters(registry):
        registry.register(Converter, name="fake-converter", summary="a converter")

    @hookimpl
    def pstoolkit_register_scenes(registry):
        registry.register(Scene, name="fake-scene", summary="a scene")

    @hookimpl
    def pstoolkit_register_integrators(registry):
        registry.register(Integrator, name="fake-integrator", summary="an integrator")

    @hookimpl
    def pstoolkit_register_renderers(registry):
        registry.register(SceneRenderer, name="fake-renderer", summary="a renderer")

    @hookimpl
    def pstoolkit_register_light_calibrations(registry):
        registry.register(LightCalibration, name="fake-calibration", summary="a light calibration")

    @hookimpl
    def pstoolkit_add_commands(app):
        @app.command()
        def fake_hello(name: str = "world") -> None:
            print(f"hello {name}")
    """


def test_markers_are_exported() -> None:
    assert pstoolkit.hookimpl is hookspecs.hookimpl is plugins.hookimpl
    assert hookspecs.hookspec.project_name == hookspecs.hookimpl.project_name == "pstoolkit"


def test_entry_point_is_discovered_with_its_version_and_attribution(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(fresh, tmp_path, {"alpha": solver_plugin("alpha-solver", option=True)}, version="1.2.3")
    assert loaded_plugins() == [PluginInfo("alpha", "pskfake_alpha", "1.2.3", "entry point")]
    entry = get_registries().solvers.get("alpha-solver")
    assert (entry.plugin, entry.summary, entry.kind) == ("alpha", "registers alpha-solver", "solver")
    assert entry.parse_options(["level=2"]) == {"level": 2.0}
    with pytest.raises(UserError, match=r"^solver 'alpha-solver' has no option 'lvl' \(options: level\)$"):
        entry.parse_options(["lvl=2"])
    assert get_registries() is get_registries()


def test_every_register_hook_fills_its_own_registry(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(fresh, tmp_path, {"all": ALL_HOOKS})
    registries = get_registries()
    expected = {
        "light_models": "fake-light",
        "shadow_detectors": "fake-shadow",
        "brdfs": "fake-brdf",
        "solvers": "fake-solver",
        "backends": "fake-backend",
        "converters": "fake-converter",
        "scenes": "fake-scene",
        "integrators": "fake-integrator",
        "renderers": "fake-renderer",
        "light_calibrations": "fake-calibration",
    }
    assert {kind: registry.names() for kind, registry in registries.items()} == {k: [v] for k, v in expected.items()}
    assert all(e.plugin == "all" for _, registry in registries.items() for e in registry)
    assert load_failures() == []


def test_add_commands_hook_adds_a_working_command(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(fresh, tmp_path, {"all": ALL_HOOKS})
    app = typer.Typer()

    @app.callback()
    def root() -> None:
        """A group, so commands are chosen by name."""

    plugins.add_commands(app)
    result = CliRunner().invoke(app, ["fake-hello", "--name", "plugin"])
    assert result.exit_code == 0, result.output
    assert result.output == "hello plugin\n"


def test_duplicate_entry_name_is_an_error_naming_both_plugins(
    fresh: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    install(fresh, tmp_path, {"alpha": solver_plugin("shared"), "beta": solver_plugin("shared")})
    message = "solver 'shared' is registered by both plugin 'alpha' and plugin 'beta'"
    with pytest.raises(PluginError) as info:
        get_registries()
    assert str(info.value) == message
    assert main(["plugins"]) == 2
    assert capsys.readouterr().err == f"pstoolkit: error: {message}\n"


def test_broken_plugin_is_reported_and_the_rest_still_load(
    fresh: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fake_distribution(
        tmp_path,
        "pskfake-mixed",
        "1.0",
        {"good": "pskfake_good", "broken": "pskfake_broken"},
        {"pskfake_good": solver_plugin("good-solver"), "pskfake_broken": "import pskfake_not_installed\n"},
    )
    fresh.syspath_prepend(str(tmp_path))
    fresh.setenv(plugins.ALLOW_ENV, "good,broken")
    error = "cannot import 'pskfake_broken': ModuleNotFoundError: No module named 'pskfake_not_installed'"
    assert get_registries().solvers.names() == ["good-solver"]
    assert [p.name for p in loaded_plugins()] == ["good"]
    assert load_failures() == [plugins.Failure("broken", error)]
    get_registries()
    assert capsys.readouterr().err == f"pstoolkit: warning: plugin 'broken': {error}\n"  # once, not per use
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert out.endswith(f"failed:\n  broken: {error}\n")
    assert "good 1.0  (pskfake_good, entry point)\n  solvers:\n    good-solver  registers good-solver\n" in out


def test_a_hook_that_raises_is_reported_and_its_other_hooks_still_run(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    source = """
        from pstoolkit import Solver, hookimpl

        class Thing(Solver):
            name = "steady"
            summary = "still registered"

        @hookimpl
        def pstoolkit_register_brdfs(registry):
            raise RuntimeError("boom\\nsecond line")

        @hookimpl
        def pstoolkit_register_solvers(registry):
            registry.register(Thing)
        """
    install(fresh, tmp_path, {"shaky": source})
    registries = get_registries()
    assert registries.solvers.names() == ["steady"] and registries.brdfs.names() == []
    assert load_failures() == [plugins.Failure("shaky", "pstoolkit_register_brdfs failed: RuntimeError: boom")]


def test_an_unknown_hook_name_is_rejected(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    source = """
        from pstoolkit import hookimpl

        @hookimpl
        def pstoolkit_register_solver(registry):
            raise AssertionError("never called")
        """
    install(fresh, tmp_path, {"typo": source})
    assert loaded_plugins() == []
    assert load_failures() == [
        plugins.Failure("typo", "implements unknown hook(s) pstoolkit_register_solver (see docs/hooks.md)")
    ]


def test_a_hook_with_arguments_the_spec_lacks_is_rejected(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    source = """
        from pstoolkit import hookimpl

        @hookimpl
        def pstoolkit_register_solvers(registry, device):
            raise AssertionError("never called")
        """
    install(fresh, tmp_path, {"args": source})
    assert loaded_plugins() == []
    (failure,) = load_failures()
    assert failure.plugin == "args"
    assert failure.error.startswith("cannot register pskfake_args: PluginValidationError: ")
    assert "\n" not in failure.error


def test_disabling_autoload_loads_no_entry_points_but_explicit_plugins(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(fresh, tmp_path, {"all": ALL_HOOKS})
    fresh.setenv(plugins.DISABLE_ENV, "1")
    assert loaded_plugins() == [] and get_registries().solvers.names() == []
    import pskfake_all  # type: ignore[import-not-found]

    plugins.register_plugin(pskfake_all, "mine")
    assert loaded_plugins() == [PluginInfo("mine", "pskfake_all", "9.9", "registered")]  # the module's __version__
    assert get_registries().scenes.get("fake-scene").plugin == "mine"
    with pytest.raises(PluginError, match=r"^plugin 'mine' is already registered$"):
        plugins.register_plugin(pskfake_all, "mine")
    fresh.setenv(plugins.DISABLE_ENV, "0")
    fresh.delenv(plugins.ALLOW_ENV)
    plugins.reset()
    assert {"all", "core"} <= {p.name for p in loaded_plugins()}  # "0" means autoload is on


def test_allow_list_loads_only_the_named_entry_points(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(fresh, tmp_path, {"alpha": solver_plugin("a"), "beta": solver_plugin("b")})
    fresh.setenv(plugins.ALLOW_ENV, " beta , ghost ")
    assert [p.name for p in loaded_plugins()] == ["beta"]
    assert get_registries().solvers.names() == ["b"]
    assert load_failures() == [
        plugins.Failure("ghost", "named in PSTOOLKIT_PLUGINS but no installed package provides it")
    ]
    assert "pskfake_alpha" not in sys.modules


def test_explicit_plugin_may_not_take_an_entry_point_name(fresh: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(fresh, tmp_path, {"alpha": solver_plugin("a")})
    import pskfake_alpha  # type: ignore[import-not-found]

    plugins.register_plugin(object(), "alpha")
    assert [p.name for p in loaded_plugins()] == ["alpha"]
    assert load_failures() == [plugins.Failure("alpha", "another plugin is already called 'alpha' (pskfake_alpha)")]
    assert loaded_plugins()[0].module == pskfake_alpha.__name__


def test_plugins_json_lists_versions_entries_and_options(
    fresh: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    install(fresh, tmp_path, {"alpha": solver_plugin("alpha-solver", option=True)}, version="1.2.3")
    assert main(["plugins", "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    assert listing == {
        "plugins": [
            {
                "name": "alpha",
                "version": "1.2.3",
                "module": "pskfake_alpha",
                "source": "entry point",
                "registered": {
                    "solvers": [
                        {
                            "name": "alpha-solver",
                            "summary": "registers alpha-solver",
                            "options": [
                                {
                                    "name": "level",
                                    "type": "float",
                                    "default": 0.5,
                                    "help": "a level",
                                    "choices": None,
                                    "minimum": 0.0,
                                    "maximum": None,
                                    "multiple": False,
                                }
                            ],
                        }
                    ]
                },
            }
        ],
        "failures": [],
    }


def test_plugins_text_without_any_plugin(fresh: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    fresh.setenv(plugins.DISABLE_ENV, "yes")
    assert main(["plugins"]) == 0
    assert capsys.readouterr().out == "no plugins loaded\n"


def test_core_plugin_registers_the_builtins_through_its_entry_point(fresh: pytest.MonkeyPatch) -> None:
    from pstoolkit.optics.brdf import GGX, Lambertian
    from pstoolkit.optics.lights import NearRingLight, RingLight, SampledLight
    from pstoolkit.sim.scenes import SCENES

    fresh.setenv(plugins.ALLOW_ENV, "core")
    (core,) = loaded_plugins()
    assert (core.name, core.module, core.version) == ("core", "pstoolkit_core", pstoolkit.__version__)
    registries = get_registries()
    assert registries.light_models.get("ring").obj is RingLight
    assert registries.light_models.get("sampled").obj is SampledLight
    assert registries.light_models.get("near-ring").obj is NearRingLight
    assert [registries.brdfs.get(n).obj for n in ("lambertian", "ggx")] == [Lambertian, GGX]
    assert registries.scenes.names() == sorted(s.name for s in SCENES)
    assert {e.plugin for _, r in registries.items() for e in r} == {"core"}
    assert load_failures() == []


class Named:
    name = "ring"
    summary = "a test entry"
    options = (Option("k", int, 1, "a count"),)


def test_registry_reads_class_attributes_and_keywords() -> None:
    registry = Registry("light model")
    entry = registry.register(Named)
    assert (entry.name, entry.obj, entry.summary, entry.options, entry.plugin) == ("ring", Named, "a test entry", Named.options, "(direct)")
    other = registry.register(object, name="plain", summary="  keyword summary ", options=[Option("x", str, "", "text")])
    assert other.summary == "keyword summary" and isinstance(other.options, tuple)
    assert registry.names() == ["plain", "ring"] and [e.name for e in registry] == ["plain", "ring"]
    assert "ring" in registry and "nope" not in registry and len(registry) == 2
    with registry.registering_for("someone"):
        assert registry.register(object, name="third", summary="s").plugin == "someone"
    assert registry.register(object, name="fourth", summary="s").plugin == "(direct)"


def test_registry_unknown_name_lists_the_known_ones() -> None:
    registry = Registry("solver")
    with pytest.raises(UserError, match=r"^unknown solver 'x' \(known: none registered\)$"):
        registry.get("x")
    registry.register(Named)
    registry.register(object, name="flat", summary="s")
    with pytest.raises(UserError, match=r"^unknown solver 'rng' \(known: flat, ring\)$"):
        registry.get("rng")


BAD_NAME = "name must be a non-empty word of letters, digits, '.', '_', '+' or '-', got"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"name": "", "summary": "s"}, f"BRDF <class 'object'>: {BAD_NAME} ''"),
        ({"name": "two words", "summary": "s"}, f"BRDF 'two words': {BAD_NAME} 'two words'"),
        ({"name": "ok", "summary": "line one\nline two"}, "BRDF 'ok': summary must be one non-empty line, got 'line one\\nline two'"),
        ({"name": "ok", "summary": " "}, "BRDF 'ok': summary must be one non-empty line, got ' '"),
        ({"name": "ok", "summary": "s", "options": ["k"]}, "BRDF 'ok': options must be a tuple of pstoolkit.plugin.options.Option"),
        (
            {"name": "ok", "summary": "s", "options": (Option("k", int, 1, "a"), Option("k", int, 2, "b"))},
            "BRDF 'ok': option 'k' is declared twice",
        ),
    ],
)
def test_registry_rejects_malformed_entries(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(PluginError) as info:
        Registry("BRDF").register(object, **kwargs)  # type: ignore[arg-type]
    assert str(info.value) == f"plugin '(direct)': {message}"


def test_registry_rejects_an_object_without_a_name() -> None:
    with pytest.raises(PluginError, match=r"^plugin 'p': scene <class 'object'>: name must be"):
        registry = Registry("scene")
        with registry.registering_for("p"):
            registry.register(object)


def test_the_same_plugin_registering_a_name_twice() -> None:
    registry = Registry("scene")
    with registry.registering_for("p"):
        registry.register(Named)
        with pytest.raises(PluginError, match=r"^scene 'ring' is registered twice by plugin 'p'$"):
            registry.register(Named)


def test_registries_refuse_an_object_of_another_kind() -> None:
    from pstoolkit.plugin.registry import Registries
    from pstoolkit.solve.base import Solver

    class Mistaken(Solver):
        name = "mistaken"
        summary = "a solver offered as a BRDF"

    registries = Registries()
    with registries.brdfs.registering_for("p"), pytest.raises(PluginError) as info:
        registries.brdfs.register(Mistaken)
    assert str(info.value) == (
        f"plugin 'p': BRDF 'mistaken' is {__name__}.{Mistaken.__qualname__}, not a subclass of pstoolkit.optics.brdf.BRDF"
    )
    assert registries.brdfs.names() == []
    with registries.backends.registering_for("p"), pytest.raises(PluginError, match="LightBackend or .*CameraSource$"):
        registries.backends.register(Mistaken)
    registries.solvers.register(Mistaken)
    assert registries.solvers.get("mistaken").obj is Mistaken


def test_a_plugin_registering_the_wrong_kind_gets_a_one_line_error(
    fresh: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    install(fresh, tmp_path, {"mixed": """
        from pstoolkit import Solver, hookimpl

        class Fit(Solver):
            name = "fit"
            summary = "a solver"

        @hookimpl
        def pstoolkit_register_brdfs(registry):
            registry.register(Fit)
        """})
    assert main(["plugins"]) == 2
    err = capsys.readouterr().err
    assert err == "pstoolkit: error: plugin 'mixed': BRDF 'fit' is pskfake_mixed.Fit, not a subclass of pstoolkit.optics.brdf.BRDF\n"


def test_built_in_plugins_load_whatever_the_environment_says(pstoolkit_plugins: pytest.MonkeyPatch, tmp_path: Path) -> None:
    install(pstoolkit_plugins, tmp_path, {"alpha": solver_plugin("a")})  # PSTOOLKIT_PLUGINS=alpha
    loaded = {p.name: p for p in loaded_plugins()}
    assert loaded["core"].source == "built in" and loaded["core"].built_in
    assert loaded["alpha"].source == "entry point" and not loaded["alpha"].built_in
    assert {"frameps", "dualres", "a"} <= set(get_registries().solvers.names())
    pstoolkit_plugins.setenv(plugins.DISABLE_ENV, "1")
    plugins.reset()
    assert "alpha" not in {p.name for p in loaded_plugins()} and "core" in {p.name for p in loaded_plugins()}


def test_a_third_party_clash_with_a_built_in_name_is_ignored_with_a_warning(
    pstoolkit_plugins: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    install(pstoolkit_plugins, tmp_path, {"copycat": """
        from pstoolkit import Solver, hookimpl

        class Impostor(Solver):
            name = "frameps"
            summary = "not the built-in frameps"

        class Own(Solver):
            name = "own"
            summary = "a solver of its own"

        @hookimpl
        def pstoolkit_register_solvers(registry):
            registry.register(Impostor)
            registry.register(Own)
        """})
    solvers = get_registries().solvers
    assert solvers.get("frameps").plugin == "frameps" and solvers.get("own").plugin == "copycat"
    message = "solver 'frameps' is built in (plugin 'frameps'); this plugin's entry is ignored"
    assert plugins.Failure("copycat", message) in load_failures()
    assert capsys.readouterr().err == f"pstoolkit: warning: plugin 'copycat': {message}\n"
    assert main(["plugins"]) == 0  # every command still works
