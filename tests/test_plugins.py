"""The plugin registry: built-ins come through entry points like third-party plugins; an unknown name
lists what is installed; a plugin that fails to import is reported and fatal only when used."""

from importlib.metadata import EntryPoint

import pytest

import pdem.plugins as plugins
from pdem.errors import PluginError


def test_builtins_are_entry_points():
    laws = plugins.available("contact_laws")
    assert laws["hertz_mindlin"].distribution == "pdem"
    assert {"plane", "box", "hopper", "outflow"} <= set(plugins.available("boundaries"))
    assert {"hdf5", "vtk"} <= set(plugins.available("writers"))


def test_unknown_name_lists_installed():
    with pytest.raises(PluginError) as err:
        plugins.load("contact_laws", "hertz_mindlinn")
    assert "Did you mean 'hertz_mindlin'" in str(err.value) and "Installed:" in str(err.value)


def test_broken_plugin_is_fatal_only_when_used(monkeypatch, capsys):
    real = plugins.entry_points
    broken = EntryPoint(name="broken_law", value="pdem_no_such_module:Law", group="pdem.contact_laws")

    def fake(group):
        eps = list(real(group=group))
        return eps + [broken] if group == "pdem.contact_laws" else eps

    monkeypatch.setattr(plugins, "entry_points", fake)
    # listing and using other plugins still works
    assert "broken_law" in plugins.available("contact_laws")
    assert plugins.load("contact_laws", "hertz_mindlin").name == "hertz_mindlin"
    from pdem.cli import main

    assert main(["plugins"]) == 0
    assert "broken_law" in capsys.readouterr().out
    # using it is a clear error
    with pytest.raises(PluginError, match="broken_law.*failed to import.*ModuleNotFoundError"):
        plugins.load("contact_laws", "broken_law")
