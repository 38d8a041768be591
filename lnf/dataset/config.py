"""DatasetConfig, the settings a dataset is generated from (checked on construction), and the comparison of a file's stored settings with them."""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields as dataclass_fields
from pathlib import Path
from typing import Any, Mapping, Optional

from lnf.dataset.format import COARSE_GRIDS, DatasetError, ERROR_HINT, FORMAT_VERSION
from lnf.utils import require


@dataclass
class DatasetConfig:
    """How a dataset is generated (stored in the file; any change regenerates it).

    Attributes:
        n_train, n_val, n_test: trajectories per split (disjoint).
        n_times: samples per trajectory; dt: sample spacing [s], t_k = dt·k, k = 0..n_times−1.
        train_times: the first samples used for training (time split; docs/method.md §7.1).
        fine_resolution: evaluation grid, fine_resolution^dim_B cell centres.
        coarse_resolution: observation grid, coarse_resolution^dim_B points.
        coarse_grid: ``"centres"``: the cell centres of that many cells per axis (the paper's); ``"vertices"``:
            that many equally spaced points per axis from one face of the box to the other, so the observations
            reach the boundary, where a field such as the pendulum's Legendre mode is largest.
        observed_fraction: fraction of the coarse grid each trajectory observes (fixed random subset).
        seed: seed of initial states and masks.
    """

    n_train: int = 32
    n_val: int = 8
    n_test: int = 16
    n_times: int = 100
    dt: float = 0.05
    train_times: int = 50
    fine_resolution: int = 64
    coarse_resolution: int = 32
    observed_fraction: float = 0.25
    seed: int = 0
    coarse_grid: str = "centres"

    def __post_init__(self) -> None:
        for key in ("n_train", "n_val", "n_test", "n_times", "train_times", "fine_resolution",
                    "coarse_resolution"):
            setattr(self, key, require(f"data.{key}", getattr(self, key), ("int", 1, None, ""), DatasetError))
        self.seed = require("data.seed", self.seed, ("int", 0, None, ""), DatasetError)
        self.dt = require("data.dt", self.dt, (">", 0, None, "", "s"), DatasetError)
        self.observed_fraction = require("data.observed_fraction", self.observed_fraction, (">", 0, 1, ""), DatasetError)
        if self.train_times > self.n_times:
            raise DatasetError(f"data.train_times must be ≤ data.n_times = {self.n_times}, got {self.train_times}")
        if self.coarse_grid not in COARSE_GRIDS:
            raise DatasetError(f"data.coarse_grid must be one of {', '.join(COARSE_GRIDS)}, got {self.coarse_grid!r}")
        if self.coarse_grid == "vertices" and self.coarse_resolution < 2:
            raise DatasetError("data.coarse_grid=vertices needs data.coarse_resolution ≥ 2 (a point on each face), "
                               f"got {self.coarse_resolution}")

    def record(self) -> dict[str, Any]:
        """The settings a file records (json-able). ``coarse_grid`` appears only when it is not the default
        "centres", so files written before the setting existed keep matching their configuration."""
        values = asdict(self)
        if values["coarse_grid"] == "centres":
            del values["coarse_grid"]
        return values

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], ignore: tuple[str, ...] = ()) -> "DatasetConfig":
        """Build from a mapping (e.g. a Hydra ``data`` node); unknown keys not in `ignore` are an error."""
        known = {f.name for f in dataclass_fields(cls)}
        unknown = sorted(set(values) - known - set(ignore))
        if unknown:
            raise DatasetError(f"unknown data setting(s) {', '.join('data.' + k for k in unknown)}; "
                               f"known: {', '.join(sorted(known))}")
        return cls(**{k: v for k, v in values.items() if k in known})

    def n_observed(self, n_coarse: int) -> int:
        """Observed coarse points per trajectory: round(observed_fraction · n_coarse)."""
        return int(round(self.observed_fraction * n_coarse))


def scene_record(scene: Any) -> dict[str, Any]:
    """The scene's spec as a file records it (JSON round trip: tuples become lists)."""
    try:
        return json.loads(json.dumps(scene.spec()))
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"scene spec of {scene!r} is not JSON-serialisable: {exc}") from exc


def generation_attributes(scene: Any, cfg: DatasetConfig) -> dict[str, Any]:
    """The json-able description a file must carry to be reused: format version, scene spec, config."""
    return {"format_version": FORMAT_VERSION, "scene": scene_record(scene), "generation": cfg.record()}


# attribute comparison: a file's stored settings against a config's
_MISSING = "<missing>"


def _flatten(value: Any, prefix: str) -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out if out else {prefix: {}}
    return {prefix: value}


def _differences(found: Mapping[str, Any], expected: Mapping[str, Any]) -> list[str]:
    """'key: file X, config Y' for each flattened key whose value differs (keys of either side)."""
    a, b = _flatten(dict(found), ""), _flatten(dict(expected), "")
    return [f"{k}: file {json.dumps(a.get(k, _MISSING))}, config {json.dumps(b.get(k, _MISSING))}"
            for k in sorted(set(a) | set(b)) if a.get(k, _MISSING) != b.get(k, _MISSING)]


def _expected(scene: Any, cfg: Optional[DatasetConfig]) -> dict[str, Any]:
    exp: dict[str, Any] = {"format_version": FORMAT_VERSION}
    if scene is not None:
        exp["scene"] = generation_attributes(scene, cfg or DatasetConfig())["scene"]
    if cfg is not None:
        exp["generation"] = cfg.record()
    return exp


def _mismatch_message(path: Path, diffs: list[str], hint: str = ERROR_HINT) -> str:
    return f"{path}: dataset was generated with different settings ({'; '.join(diffs)}); {hint}"


def _kept_message(path: Path, detail: str) -> str:
    """A file at an explicit path made with other settings: not overwritten; the differences and the fixes."""
    return (f"{path}: the file at this explicitly given data.path was generated with other settings ({detail}; "
            f"'file' = the settings of the run that generated it, 'config' = this run's). A file at an explicit "
            f"data.path is not overwritten with other settings (another run may be using it): give these settings "
            f"another data.path, or set data.path=null (path: null) for one file per setting set under "
            f"data.data_dir, or delete the file to regenerate it")


