"""The package's public API, and the old module paths from before the engine was laid out by concept."""

import importlib
import os
import subprocess
import sys

import pytest

import semantic_gs_slam
from semantic_gs_slam import _moved

PACKAGE_DIR = os.path.dirname(semantic_gs_slam.__file__)


def test_public_api_imports_lazily():
    code = ("import sys, semantic_gs_slam\n"
            "assert 'torch' not in sys.modules, 'import semantic_gs_slam pulled torch in'\n"
            "from semantic_gs_slam import SLAM, SlamConfig, load_dataset\n"
            "import semantic_gs_slam.io.datasets as d, semantic_gs_slam.slam as s\n"
            "assert SLAM is s.SLAM and load_dataset is d.load_dataset and SlamConfig.__name__ == 'SlamConfig'\n")
    r = subprocess.run([sys.executable, "-W", "error::DeprecationWarning", "-c", code], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    with pytest.raises(AttributeError, match="no_such_name"):
        semantic_gs_slam.no_such_name  # noqa: B018


@pytest.mark.parametrize("old", sorted(_moved.MOVED))
def test_an_old_module_path_yields_the_new_module_with_a_warning(old, monkeypatch):
    new = importlib.import_module(_moved.MOVED[old])
    monkeypatch.delitem(sys.modules, old, raising=False)  # an earlier import of the old path would hide the warning
    with pytest.warns(DeprecationWarning, match=f"{old} moved to {_moved.MOVED[old]}") as warned:
        mod = importlib.import_module(old)
    assert mod is new  # the same object: patching either name patches both
    assert mod.__name__ == new.__spec__.name == _moved.MOVED[old]  # the module keeps its own name and spec
    assert not os.path.exists(os.path.join(PACKAGE_DIR, old.split(".", 1)[1] + ".py"))  # no shim file left
    assert warned[0].filename.endswith("importlib/__init__.py")  # blamed on the importer (here import_module)


@pytest.mark.parametrize("package", sorted(_moved.RENAMED_TO_PACKAGE))
def test_names_of_an_old_module_that_became_a_package_are_forwarded(package, monkeypatch):
    pkg = importlib.import_module(package)
    target = importlib.import_module(_moved.RENAMED_TO_PACKAGE[package])
    name = next(n for n in sorted(vars(target)) if not n.startswith("_") and callable(getattr(target, n))
                and getattr(getattr(target, n), "__module__", None) == target.__name__)
    monkeypatch.delitem(vars(pkg), name, raising=False)
    with pytest.warns(DeprecationWarning, match=f"{package}.{name} moved to {target.__name__}.{name}") as warned:
        value = getattr(pkg, name)
    assert value is getattr(target, name)
    assert warned[0].filename == __file__
    with pytest.raises(AttributeError, match="no_such_name"):
        pkg.no_such_name  # noqa: B018


def test_a_from_import_of_an_old_path_blames_the_importing_line(tmp_path):
    script = tmp_path / "user.py"
    script.write_text("import warnings\nwarnings.simplefilter('always')\nimport semantic_gs_slam.datasets\n"
                      "from semantic_gs_slam.tracking import icp\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"{script}:3: DeprecationWarning: semantic_gs_slam.datasets moved to semantic_gs_slam.io." in r.stderr
    assert f"{script}:4: DeprecationWarning: semantic_gs_slam.tracking.icp moved to" in r.stderr
    assert r.stderr.count("DeprecationWarning") == 2  # the forwarded name warns once


COMMANDS = ["semantic_gs_slam.io.calibrate_colour", "semantic_gs_slam.synthetic.demo_map",
            "semantic_gs_slam.colour_registration", "semantic_gs_slam.demo_map", "semantic_gs_slam.synthetic",
            "semantic_gs_slam.run", "semantic_gs_slam.labels.names"]


def test_documented_commands_still_run_without_a_warning():
    # runpy.run_module finds and runs a module as ``python -m`` does (find_spec, then the loader's code as __main__);
    # one process for them all (each imports torch); the old names of two of them too
    code = ("import contextlib, io, runpy, sys\n"
            f"for cmd in {COMMANDS!r}:\n"
            "    sys.argv = [cmd, '--help']\n"
            "    out = io.StringIO()\n"
            "    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):\n"
            "        runpy.run_module(cmd, run_name='__main__', alter_sys=True)\n"
            "    assert out.getvalue().startswith('usage: '), (cmd, out.getvalue())\n"
            "    print(cmd, 'ok')\n")
    r = subprocess.run([sys.executable, "-W", "error::DeprecationWarning", "-c", code], capture_output=True,
                       text=True, timeout=240)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [w for c in COMMANDS for w in (c, "ok")]


def test_the_colour_calibration_command_reports_a_bad_dataset(tmp_path):
    # the real ``python -m OLD`` path: the old name's code is the command module's, run as __main__
    r = subprocess.run([sys.executable, "-m", "semantic_gs_slam.colour_registration", str(tmp_path / "none")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and str(tmp_path / "none") in r.stderr
