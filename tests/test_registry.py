"""Entry-point discovery, with a real faulty plugin distribution installed by pip."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fallkit import registry
from fallkit.api import PluginError, RobotSpec, get_robot, list_robots

PLUGIN = Path(__file__).parent / "plugins" / "fallkit-testplugins"


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory) -> Path:
    """pip-install the faulty test plugin into a private directory (not the venv)."""
    target = tmp_path_factory.mktemp("site")
    source = tmp_path_factory.mktemp("src") / PLUGIN.name  # build from a copy: no build/ in the tree
    shutil.copytree(PLUGIN, source)
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
         "--no-index", "--target", str(target), str(source)],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    return target


@pytest.fixture
def with_plugin(plugin_site, monkeypatch):
    monkeypatch.syspath_prepend(str(plugin_site))
    registry.clear_cache()
    yield
    registry.clear_cache()


def test_builtins_come_through_entry_points():
    entry = registry.entries("fallkit.robots")["biped20"]
    assert entry.distribution == "fallkit"
    assert entry.entry_point.value == "fallkit.robots.biped20:biped20"
    assert {"biped20", "biped20_battery"} <= set(list_robots())
    assert isinstance(get_robot("biped20"), RobotSpec)


def test_unknown_name_lists_what_exists():
    with pytest.raises(PluginError, match=r"unknown robot 'nosuch'; registered robots: .*biped20"):
        get_robot("nosuch")


def test_valid_third_party_robot(with_plugin):
    spec = get_robot("tiny_biped")
    assert spec.joint_names == ["neck_yaw", "neck_pitch"]
    assert registry.scan("fallkit.robots")[0]["tiny_biped"].distribution == "fallkit-testplugins"


def test_import_failure_names_distribution_and_entry_point(with_plugin):
    with pytest.raises(PluginError) as err:
        get_robot("broken_robot")
    msg = str(err.value)
    assert "fallkit-testplugins" in msg and "broken_robot = fallkit_testplugins.broken:robot" in msg
    assert "failed to import" in msg and "a_module_that_does_not_exist" in msg


def test_invalid_value_names_distribution(with_plugin):
    with pytest.raises(PluginError, match=r"not_a_spec = .*fallkit-testplugins.*expected a RobotSpec"):
        get_robot("not_a_spec")
    with pytest.raises(PluginError, match=r"not_callable.*expected a reward term function"):
        registry.load("fallkit.rewards", "not_callable")


def test_duplicate_name_is_an_error_naming_both(with_plugin):
    with pytest.raises(PluginError) as err:
        get_robot("biped20")
    msg = str(err.value)
    assert "registered 2 times" in msg and "'fallkit'" in msg and "'fallkit-testplugins'" in msg
    # other names stay usable
    assert get_robot("biped20_battery").name == "biped20_battery"


def test_every_name_of_the_plugin_api_resolves_and_type_checkers_see_the_same_imports():
    """fallkit.api imports its names on first use: each name in __all__ must resolve, and the TYPE_CHECKING
    imports that editors read must name the same modules and names as the lazy table."""
    import ast
    import inspect

    import fallkit.api as api

    for name in api.__all__:
        assert getattr(api, name) is not None, name
    tree = ast.parse(inspect.getsource(api))
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    seen = {i.module: tuple(a.name for a in i.names) for i in block.body if isinstance(i, ast.ImportFrom)}
    assert seen == api._LAZY
    with pytest.raises(AttributeError, match="no attribute 'nosuch'"):
        api.nosuch  # noqa: B018
