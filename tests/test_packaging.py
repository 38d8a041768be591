"""Packaging: the console scripts find their configs from any directory (the top-level conf/ ships inside the
package as ``lnf.conf``, read with ``@hydra.main(config_path="pkg://lnf.conf")``), the packaged configs are the
repository's conf/, and LICENSE, CITATION.cff and the py.typed marker are in place and agree with pyproject.toml.
"""
import os
import shutil
import subprocess
import sys
import sysconfig
from importlib.resources import files

import pytest
import yaml

from helpers import ROOT

# the console-script tests share one module fixture (two subprocesses): keep them on one pytest-xdist worker
pytestmark = pytest.mark.xdist_group("packaging")

CONF = ROOT / "conf"


def _pyproject() -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        tomllib = pytest.importorskip("tomli", reason="reading pyproject.toml on Python 3.10 needs tomli")
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _options(group: str) -> str:
    """The line Hydra's --help prints for a config group of conf/: `group: a, b, c`."""
    return f"{group}: " + ", ".join(sorted(p.stem for p in (CONF / group).glob("*.yaml")))


EXAMPLE_CONF = ROOT / "examples" / "conf"
# the installed console scripts (the files `pip install` writes), each with --help; lnf-train also with a config
# folder of one's own, whose options Hydra adds to the packaged ones (the primary config stays lnf.conf's)
HELP = {"lnf-train": ["--config-dir", str(EXAMPLE_CONF), "--help"], "lnf-evaluate": ["--help"]}


@pytest.fixture(scope="module")
def helps(tmp_path_factory):
    """Each console script's --help, run from an empty temporary directory; both at once (each imports torch and
    Lightning, several seconds): script -> (exit status, stdout, stderr), or None when it is not on PATH."""
    cwd = tmp_path_factory.mktemp("elsewhere")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # as a user's shell has it: lnf as installed
    started = {}
    for script, args in HELP.items():
        exe = shutil.which(script)
        started[script] = exe and subprocess.Popen([exe, *args], cwd=cwd, env=env, text=True,
                                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    done = {}
    for script, proc in started.items():
        if proc:
            try:
                out, err = proc.communicate(timeout=120)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, err = proc.communicate()
            done[script] = (proc.returncode, out, err)
        else:
            done[script] = None
    return done


def _help(helps, script: str) -> str:
    if helps[script] is None:
        pytest.skip(f"the console script {script} is not on PATH: install lnf (pip install -e .) to test it")
    status, out, err = helps[script]
    assert status == 0, f"{script} {' '.join(HELP[script])} failed outside the repository:\n{out}\n{err}"
    return out


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(HELP))
def test_the_console_scripts_find_their_configs_from_any_directory(helps, script):
    out = _help(helps, script)
    assert "== Configuration groups ==" in out
    for group in ("scene", "integrator", "quadrature", "trainer", "logger"):
        assert _options(group) in out, f"{script} --help does not list the {group} options of conf/{group}:\n{out}"


@pytest.mark.slow
def test_a_config_dir_of_ones_own_adds_its_options_to_the_packaged_ones(helps):
    out = _help(helps, "lnf-train")
    own = {p.stem for p in (EXAMPLE_CONF / "experiment").glob("*.yaml")}
    line = "experiment: " + ", ".join(sorted(own | {p.stem for p in (CONF / "experiment").glob("*.yaml")}))
    assert own and line in out, out


def _tree(node, prefix: str = "") -> dict[str, bytes]:
    """Every .yaml file below an importlib.resources Traversable, by relative path, with its bytes."""
    found = {}
    for child in node.iterdir():
        rel = f"{prefix}{child.name}"
        if child.is_dir():
            found.update(_tree(child, rel + "/"))
        elif child.name.endswith(".yaml"):
            found[rel] = child.read_bytes()
    return found


def test_the_packaged_configs_are_the_repositorys_conf_folder():
    try:
        packaged = _tree(files("lnf.conf"))
    except ModuleNotFoundError:
        pytest.fail("lnf.conf is not importable: install lnf (pip install -e .), which maps conf/ to lnf.conf")
    repo = {p.relative_to(CONF).as_posix(): p.read_bytes() for p in CONF.rglob("*.yaml")}
    assert {"train.yaml", "evaluate.yaml", "hydra/launcher/slurm.yaml"} <= set(repo)
    assert sorted(packaged) == sorted(repo), "lnf.conf (as installed) and conf/ list different files: reinstall lnf"
    stale = [name for name in repo if packaged[name] != repo[name]]
    assert not stale, f"the installed lnf.conf differs from conf/ in {stale}: reinstall lnf (pip install -e .)"
    assert (CONF / "__init__.py").is_file(), "Hydra's pkg:// config source needs conf/ to be a package"


def test_pyproject_ships_every_package_the_configs_and_the_type_marker():
    pyproject = _pyproject()
    setuptools = pyproject["tool"]["setuptools"]
    packages = set(setuptools["packages"])
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "lnf").rglob("__init__.py")}
    assert on_disk <= packages, f"pyproject.toml [tool.setuptools] packages lacks {sorted(on_disk - packages)}"
    assert packages - on_disk == {"lnf.conf"}, sorted(packages - on_disk)
    assert setuptools["package-dir"] == {"lnf.conf": "conf"}
    assert "**/*.yaml" in setuptools["package-data"]["lnf.conf"] and "*.yaml" in setuptools["package-data"]["lnf.conf"]
    assert "py.typed" in setuptools["package-data"]["lnf"]
    assert (ROOT / "lnf" / "py.typed").is_file()
    scripts = pyproject["project"]["scripts"]
    assert scripts == {"lnf-train": "lnf.train:main", "lnf-evaluate": "lnf.evaluate:main"}


def test_license_and_citation_metadata():
    pyproject = _pyproject()
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert text.startswith("MIT License") and "Copyright (c) 2026 the lnf developers" in text
    assert pyproject["project"]["license"] in ({"text": "MIT"}, "MIT")

    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    for key in ("cff-version", "message", "title", "authors"):  # the keys CFF 1.2.0 requires
        assert cff.get(key), f"CITATION.cff lacks {key}"
    assert str(cff["cff-version"]) == "1.2.0" and cff["type"] == "software" and cff["title"] == "lnf"
    assert str(cff["version"]) == pyproject["project"]["version"], "CITATION.cff's version is not pyproject's"
    assert cff["license"] == "MIT" and cff["abstract"]
    assert all(isinstance(a, dict) and (a.get("name") or a.get("family-names")) for a in cff["authors"])
    paper = cff["preferred-citation"]
    for key in ("type", "title", "authors"):  # the keys a CFF reference requires
        assert paper.get(key), f"CITATION.cff's preferred-citation lacks {key}"
    assert paper["title"] == "Lagrangian Neural Fields for Infinite-Dimensional Dynamics Modeling"


def test_lnf_exposes_its_version_consistently():
    from importlib.metadata import version

    import lnf

    assert lnf.__version__ == _pyproject()["project"]["version"] == version("lnf"), \
        "lnf.__version__, pyproject.toml and the installed metadata disagree: reinstall lnf (pip install -e .)"



def test_a_checkout_on_pythonpath_alone_finds_its_configs(tmp_path):
    """Without any install (the editable finder removed, only PYTHONPATH=<checkout>), `lnf.conf` is the checkout's
    conf/ and Hydra composes the training config from it."""
    # python -S skips the site module, so no .pth file (the editable install's finder) runs; the installed packages
    # come from PYTHONPATH, after the checkout
    code = (
        "import lnf, lnf.conf\n"
        "from hydra import compose, initialize_config_module\n"
        "with initialize_config_module('lnf.conf', version_base=None):\n"
        "    cfg = compose('train')\n"
        "print(lnf.conf.__file__, cfg.model.width)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), sysconfig.get_paths()["purelib"]])}
    proc = subprocess.run([shutil.which("python") or "python", "-S", "-c", code], cwd=tmp_path, env=env, text=True,
                          capture_output=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    path, width = proc.stdout.split()
    assert path == str(CONF / "__init__.py")
    assert int(width) == yaml.safe_load((CONF / "model" / "lnf.yaml").read_text())["width"]


def test_another_checkout_on_pythonpath_reads_its_own_configs(tmp_path):
    """A second checkout (e.g. an older commit in a git worktree) put first on PYTHONPATH beside an installed lnf
    composes its own conf/, not the installed package's (a baseline's configs must be the baseline's)."""
    other = tmp_path / "checkout"
    shutil.copytree(ROOT / "lnf", other / "lnf", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(CONF, other / "conf", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", other / "pyproject.toml")
    model = other / "conf" / "model" / "lnf.yaml"
    model.write_text(model.read_text().replace("width: 256", "width: 77"))
    code = ("import lnf, lnf.conf\n"
            "from hydra import compose, initialize_config_module\n"
            "with initialize_config_module('lnf.conf', version_base=None):\n"
            "    cfg = compose('train')\n"
            "print(lnf.__file__, lnf.conf.__file__, cfg.model.width)\n")
    env = {**os.environ, "PYTHONPATH": str(other)}
    proc = subprocess.run([shutil.which("python") or "python", "-c", code], cwd=tmp_path, env=env, text=True,
                          capture_output=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    package, configs, width = proc.stdout.split()
    assert package == str(other / "lnf" / "__init__.py") and configs == str(other / "conf" / "__init__.py")
    assert int(width) == 77


def test_python_dash_m_lnf_lists_the_entry_points(tmp_path, capsys):
    """`python -m lnf` (lnf/__main__.py) prints the entry points and exits 0, from any directory; an unknown
    command exits 2 and a sweep-table of a folder without jobs exits 1, each with a message."""
    proc = subprocess.run([sys.executable, "-m", "lnf"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    for entry in ("python -m lnf.train", "python -m lnf.evaluate", "lnf-train", "lnf-evaluate", "python -m lnf.train -m",
                  "sweep_table.csv", "python -m lnf sweep-table", "outputs/<scene>/runs/<date>/"):
        assert entry in proc.stdout, f"python -m lnf does not list {entry}:\n{proc.stdout}"
    assert set(_pyproject()["project"]["scripts"]) <= set(proc.stdout.split()), "a console script is not listed"

    from lnf.__main__ import main

    assert main(["no-such-command"]) == 2 and "unknown command" in capsys.readouterr().err
    assert main(["sweep-table", str(tmp_path)]) == 1 and "holds no job" in capsys.readouterr().err
