"""The params files in config/ are exactly what the nodes declare (generated, never hand-edited)."""

from pathlib import Path

import pytest
import yaml

from mpm_monitor.nodes.params_files import NODES, render

CONFIG = Path(__file__).resolve().parent.parent / "config"


@pytest.mark.parametrize("node", sorted(NODES))
def test_params_file_matches_the_declared_parameters(node):
    path = CONFIG / f"{node}.yaml"
    assert path.read_text(encoding="utf-8") == render(node), (
        f"{path} is out of date: run python -m mpm_monitor.nodes.params_files")


@pytest.mark.parametrize("node", sorted(NODES))
def test_params_file_values_are_the_defaults(node):
    import importlib

    params = importlib.import_module(f"mpm_monitor.nodes.{NODES[node][0]}").PARAMS
    values = yaml.safe_load((CONFIG / f"{node}.yaml").read_text())[f"/**/{node}"]["ros__parameters"]
    for spec in params:
        if spec.default is None:
            assert spec.name not in values
        else:
            got = values[spec.name]
            assert spec.check(got) == spec.check(spec.default), spec.name


def test_readme_parameter_tables_are_current():
    from mpm_monitor.nodes.params_files import markdown

    readme = (CONFIG.parent / "README.md").read_text(encoding="utf-8")
    for node in NODES:
        assert markdown(node) in readme, f"README parameter table of {node} is out of date"
