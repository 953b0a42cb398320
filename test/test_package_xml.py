"""package.xml names what the code imports, with keys that rosdep resolves.

Every key below was looked up in ros/rosdistro at commit 8468e88ccd52 (2026-08-22): the Python keys
in ``rosdep/python.yaml`` (each has an ``ubuntu`` entry), the ROS packages among the released
packages of ``jazzy/distribution.yaml``.  A new dependency is looked up the same way and added here.
osqp has no key there (nor ``python3-osqp-pip``); python-control has ``python-control-pip`` but no
``python3-control-pip``.
"""

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: ROS 2 Jazzy packages the code imports (their names are their rosdep keys).
ROS_PACKAGES = {"rclpy", "rcl_interfaces", "std_msgs", "sensor_msgs", "diagnostic_msgs", "rosgraph_msgs",
                "std_srvs", "builtin_interfaces", "ament_index_python"}
#: Python module imported -> its rosdep key.
PYTHON_KEYS = {"numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml",
               "matplotlib": "python3-matplotlib", "rosbags": "python3-rosbags-pip",
               "pytest": "python3-pytest", "hypothesis": "python3-hypothesis", "control": "python-control-pip",
               "colcon_core": "python3-colcon-common-extensions"}
#: Keys of packages used without an import (pytest plugins).
OTHER_KEYS = {"python3-pytest-timeout"}
#: Imported by the tests only, with no rosdep key: installed with pip (README, "Use in a ROS 2 workspace").
PIP_ONLY = {"osqp"}
#: The repository's own modules that the tests import: the benchmarks, and the test folder's modules
#: (helpers such as report_checks, and test modules whose simulations other tests reuse).
REPOSITORY_MODULES = {"bench"} | {p.stem for p in (ROOT / "test").glob("*.py")}


def dependencies(*tags) -> set:
    root = ET.parse(ROOT / "package.xml").getroot()
    return {el.text.strip() for tag in tags for el in root.iter(tag)}


def imported_modules(paths) -> set:
    """Top-level names of the absolute imports in ``paths``, less the standard library."""
    names = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module.split(".")[0])
    return names - set(sys.stdlib_module_names) - {"__future__", "mpm_monitor"}


def key_of(module: str) -> str:
    return module if module in ROS_PACKAGES else PYTHON_KEYS.get(module, f"<no key for {module}>")


def test_every_dependency_is_a_checked_key():
    checked = ROS_PACKAGES | set(PYTHON_KEYS.values()) | OTHER_KEYS
    assert dependencies("depend", "exec_depend", "test_depend", "build_depend", "buildtool_depend") <= checked


def test_every_import_of_the_package_is_an_exec_dependency():
    modules = imported_modules((ROOT / "mpm_monitor").rglob("*.py"))
    assert {m: key_of(m) for m in modules if key_of(m) not in dependencies("depend", "exec_depend")} == {}


def test_the_package_installs_only_what_package_xml_declares():
    # setup.py's install_requires (pip's view of the package) holds no module without a rosdep key.
    tree = ast.parse((ROOT / "setup.py").read_text(encoding="utf-8"))
    requires = next(kw.value for node in ast.walk(tree) if isinstance(node, ast.Call)
                    for kw in node.keywords if kw.arg == "install_requires")
    names = {ast.literal_eval(e).lower() for e in requires.elts}
    assert not names & PIP_ONLY, names


def test_every_import_of_the_tests_is_a_dependency_or_the_pip_step():
    modules = imported_modules((ROOT / "test").glob("*.py")) - PIP_ONLY - REPOSITORY_MODULES
    deps = dependencies("depend", "exec_depend", "test_depend")
    assert {m: key_of(m) for m in modules if key_of(m) not in deps} == {}


def test_the_pip_step_installs_what_has_no_key_at_the_version_tested_here():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Use in a ROS 2 workspace", 1)[1].split("\n## ", 1)[0]
    pins = dict(re.findall(r"^([A-Za-z0-9_.-]+)==(\S+)", (ROOT / "requirements.txt").read_text(), re.M))
    for name in PIP_ONLY:
        assert re.search(rf"pip install .*\b{name}=={re.escape(pins[name])}\b", section), name
