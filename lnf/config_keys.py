"""Refuse config keys that a command does not use (``+scene=pendulum`` or ``+foo=1`` given to ``lnf.evaluate``).

Hydra accepts any ``+key=value`` override and merges it into the composed config, where a command that never
reads the key silently ignores it (and its run record then shows a setting that had no effect). The keys a
command takes are derived from its primary config file, ``conf/<name>.yaml``:

* the file's own keys (except ``defaults``), and for its plain nested nodes (such as ``grid``) their sub-keys,
  recursively (a value that is not a mapping, e.g. ``initial_states: null``, may hold anything);
* the config groups its defaults list names (``integrator``, ``quadrature``, ...; a group's content is not
  checked here), and ``hydra``;
* the keys that the options of those groups write at the top level with ``# @package _global_`` (for example
  ``conf/dynamics/latent_mlp.yaml``), merged the same way;
* ``allowed_extra``: more config groups (a directory of the config dir, e.g. ``experiment`` for ``lnf.train``,
  whose ``_global_`` options add keys such as ``tags``) or keys, dotted for nested ones (``grid.extra``).
"""
from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Any, Iterable, Optional, Union

from omegaconf import DictConfig, OmegaConf

def _conf_dir() -> Path:
    """The configs the entry points compose (``@hydra.main(config_path="pkg://lnf.conf")``): the installed package's
    ``lnf/conf``, which an editable install maps to the repository's ``conf/``."""
    from importlib.resources import files

    return Path(str(files("lnf.conf")))


CONF_DIR = _conf_dir()

# A tree of accepted keys: key -> None (anything below it) or a nested tree (only those sub-keys).
KeyTree = dict[str, Optional[dict]]

_GLOBAL = re.compile(r"^\s*#\s*@package\s+_global_\s*$")


def _primary_path(primary: Union[str, Path]) -> Path:
    """`conf/<name>.yaml` for a name ("evaluate" or "evaluate.yaml"), else the path as given."""
    path = Path(primary)
    if len(path.parts) == 1 and not path.is_file():
        path = CONF_DIR / (path.name if path.suffix == ".yaml" else f"{path.name}.yaml")
    if not path.is_file():
        raise FileNotFoundError(f"primary config {path} not found: cannot tell which keys it takes")
    return path


def _is_global(path: Path) -> bool:
    """Whether a config file starts with a `# @package _global_` header (in its leading comment lines)."""
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        if not line.lstrip().startswith("#"):
            return False
        if _GLOBAL.match(line):
            return True
    return False


def _tree(node: Any) -> Optional[dict]:
    """The key tree of a plain mapping node (None for anything else)."""
    if not isinstance(node, DictConfig) or node._is_none() or node._is_missing() or node._is_interpolation():
        return None
    return {str(k): _tree(node._get_node(k)) for k in node.keys()}


def _merge(into: KeyTree, key: str, sub: Optional[dict]) -> None:
    """Add `key` with sub-tree `sub` to `into`: None (anything) wins over a tree; trees are united."""
    if key not in into:
        into[key] = sub
    elif into[key] is not None:
        if sub is None:
            into[key] = None
        else:
            for k, v in sub.items():
                _merge(into[key], k, v)


def _group_of(entry: Any) -> Optional[str]:
    """The config group a defaults-list entry selects (None for `_self_` and plain config names)."""
    if not isinstance(entry, (dict, DictConfig)) or len(entry) != 1:
        return None
    key = str(next(iter(entry.keys())))
    for prefix in ("override ", "optional "):
        key = key[len(prefix):] if key.startswith(prefix) else key
    return key.strip().lstrip("/").split("@")[0] or None


def _add_group(tree: KeyTree, conf_dir: Path, group: str, package: Optional[str] = None) -> None:
    """A config group: its key is accepted with any content; its `_global_` options' keys are merged in."""
    top = group.split("/")[0]
    if top == "hydra":
        return
    if package and not package.startswith("_global_"):
        _merge(tree, package.split(".")[0], None)
    elif not package:
        _merge(tree, top, None)
    folder = conf_dir / group
    if not folder.is_dir():
        return
    for option in sorted(folder.rglob("*.yaml")):
        if package and package.startswith("_global_") or _is_global(option):
            loaded = OmegaConf.load(option)
            if isinstance(loaded, DictConfig):
                for k in loaded.keys():
                    if k not in ("defaults", "hydra"):
                        _merge(tree, str(k), _tree(loaded._get_node(k)))


def allowed_keys(primary: Union[str, Path], allowed_extra: Iterable[str] = ()) -> KeyTree:
    """The key tree that the primary config file `primary` (a name in conf/ or a path) accepts."""
    path = _primary_path(primary)
    conf_dir = path.parent
    loaded = OmegaConf.load(path)
    tree: KeyTree = {}
    if isinstance(loaded, DictConfig):
        for k in loaded.keys():
            if k != "defaults":
                _merge(tree, str(k), _tree(loaded._get_node(k)))
        for entry in loaded.get("defaults") or []:
            group = _group_of(entry)
            if group:
                raw = str(next(iter(entry.keys())))
                _add_group(tree, conf_dir, group, raw.split("@", 1)[1] if "@" in raw else None)
    for extra in allowed_extra:
        extra = str(extra)
        if (conf_dir / extra).is_dir():
            _add_group(tree, conf_dir, extra)
        else:
            node = tree
            *parents, last = extra.split(".")
            for part in parents:
                if node.get(part, {}) is None:
                    break
                node = node.setdefault(part, {})
            else:
                _merge(node, last, None)
    tree["hydra"] = None
    return tree


def _unknown(cfg: DictConfig, tree: KeyTree, prefix: str = "") -> list[str]:
    """Dotted keys of `cfg` that `tree` does not accept."""
    bad = []
    for k in cfg.keys():
        key = f"{prefix}{k}"
        if k not in tree:
            bad.append(key)
        elif tree[k] is not None:
            child = cfg._get_node(k)
            if isinstance(child, DictConfig) and not child._is_none() and not child._is_missing():
                bad += _unknown(child, tree[k], f"{key}.")
    return bad


def check_known_keys(cfg: DictConfig, primary: Union[str, Path], command: str,
                     allowed_extra: Iterable[str] = ()) -> None:
    """Raise ValueError naming every key of the composed `cfg` that `command` does not use.

    Args:
        cfg: the composed config (with or without its `hydra` node).
        primary: the command's primary config: a name in conf/ ("evaluate") or the path of a .yaml file.
        command: how the message names the command ("lnf.evaluate").
        allowed_extra: more config groups or (dotted) keys to accept, see the module docstring.
    """
    if not isinstance(cfg, DictConfig):
        raise TypeError(f"check_known_keys needs a DictConfig, got {type(cfg).__name__}")
    path = _primary_path(primary)
    tree = allowed_keys(path, allowed_extra)
    bad = _unknown(cfg, tree)
    if not bad:
        return
    loaded = OmegaConf.load(path)
    groups = [g.split("/")[0] for g in (_group_of(e) for e in (loaded.get("defaults") or [])) if g]
    groups = [g for g in dict.fromkeys(groups) if g != "hydra"]
    groups += [str(e) for e in allowed_extra if (path.parent / str(e)).is_dir() and str(e) not in groups]
    own = [k for k in tree if k not in groups and k != "hydra"]
    lines = [f"{command} does not use the key(s) {', '.join(sorted(bad))} (given as +key=value overrides, or set by "
             f"a config it does not take); it takes {', '.join(own)}"
             + (f" and the config groups {', '.join(groups)}" if groups else "") + f" (from {path})"]
    parents = dict.fromkeys(b.rpartition(".")[0] for b in sorted(bad) if "." in b)
    for parent in parents:
        node: Any = tree
        for part in parent.split("."):
            node = node[part]
        lines.append(f"{parent} takes {', '.join(node)}")
    hints = []
    for b in sorted(bad):
        parent, _, leaf = b.rpartition(".")
        node = tree
        for part in (parent.split(".") if parent else []):
            node = node[part]
        close = difflib.get_close_matches(leaf, list(node), n=1)
        if close:
            hints.append(f"{(parent + '.') if parent else ''}{close[0]} instead of {b}")
    if hints:
        lines.append(f"did you mean {', '.join(hints)}?")
    raise ValueError("; ".join(lines))
