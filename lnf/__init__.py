"""lnf — Lagrangian neural fields: structure-preserving, discretization-agnostic reduced-order models
of continuum mechanics (modulated SIREN embedding, K-step reduction, pulled-back Lagrangian dynamics).

    model = lnf.load("outputs/pendulum/runs/<date>/checkpoints/last.ckpt")
"""
import importlib.util as _ilu
import sys as _sys
from pathlib import Path as _Path


def _map_repository_configs() -> None:
    """Make ``lnf.conf`` importable from a checkout used without installing (only ``PYTHONPATH``): an install
    ships the repository's ``conf/`` as ``lnf.conf``; here it is mapped onto the same folder by hand. A checkout
    beside which another one is installed (a git worktree of an older commit, say) reads its own ``conf/``, not
    the installed one's."""
    if "lnf.conf" in _sys.modules:
        return
    root = _Path(__file__).resolve().parent.parent
    init = root / "conf" / "__init__.py"
    own = init.is_file() and (root / "pyproject.toml").is_file()  # this lnf is a repository's, with its conf/
    try:
        found = _ilu.find_spec("lnf.conf")
    except (ImportError, ValueError):
        found = None
    if found is not None and (not own or _Path(found.origin or "").resolve() == init.resolve()):
        return
    if own:
        spec = _ilu.spec_from_file_location("lnf.conf", init, submodule_search_locations=[str(init.parent)])
        if spec is not None and spec.loader is not None:
            module = _ilu.module_from_spec(spec)
            _sys.modules["lnf.conf"] = module
            spec.loader.exec_module(module)
            globals()["conf"] = module


_map_repository_configs()

from lnf.integrators import RK4, Dopri5, ImplicitMidpoint, RolloutDivergedError, get_integrator
from lnf.model import LagrangianNeuralField, build, load
from lnf.quadrature import GaussLegendre, GivenPoints, Quadrature, UniformGrid, midpoint_grid
from lnf.scenes import LiftedPendulum, Scene

__version__ = "0.1.0"

__all__ = ["load", "build", "LagrangianNeuralField", "LiftedPendulum", "Scene", "Quadrature", "GaussLegendre",
           "UniformGrid", "GivenPoints", "midpoint_grid", "RK4", "ImplicitMidpoint", "Dopri5", "get_integrator",
           "RolloutDivergedError", "__version__"]
