"""Loads openpi params checkpoints (e.g. pi0_base's `params/` directory) into a preset, strictly.

openpi writes params with `orbax.checkpoint.PyTreeCheckpointer` as `{"params": nested dict}`;
checkpoints saved during openpi training carry NNX's extra `value` level on every leaf. Both are
read here. The checkpoint's tree is compared against the preset's parameter tree from the orbax
metadata, before any array is read: every missing, unexpected or mis-shaped key is listed in one
ValueError. Arrays are restored as float32. A model with LoRA adapters (`model.lora`) reads a
checkpoint with them (a LoRA fine-tune) or without any (the base model, openpi's way to start a
LoRA fine-tune): then the adapters start from their random init.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from pi0_armfix.model.config import Pi0Config
from pi0_armfix.model.flow_model import Params, init_params, param_shapes
from pi0_armfix.model.gemma import is_adapter

_SEP = "/"


def _flatten(tree: Mapping[str, Any], prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            flat.update(_flatten(value, prefix + (key,)))
        else:
            flat[prefix + (key,)] = value
    return flat


def _unflatten(flat: Mapping[tuple[str, ...], Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for path, value in flat.items():
        node = tree
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = value
    return tree


def check_tree(found: Mapping[tuple[str, ...], tuple[int, ...]],
               expected: Mapping[tuple[str, ...], tuple[int, ...]], source: str) -> None:
    """Raises one ValueError listing missing, unexpected and mis-shaped keys ("a/b/c")."""
    missing = sorted(_SEP.join(p) for p in expected.keys() - found.keys())
    unexpected = sorted(_SEP.join(p) for p in found.keys() - expected.keys())
    misshaped = sorted(f"{_SEP.join(p)}: checkpoint {tuple(found[p])} != model {tuple(expected[p])}"
                       for p in expected.keys() & found.keys() if tuple(found[p]) != tuple(expected[p]))
    problems = [f"{title} ({len(keys)}): {', '.join(keys)}" for title, keys in
                (("missing keys", missing), ("unexpected keys", unexpected),
                 ("mis-shaped keys", misshaped)) if keys]
    if problems:
        raise ValueError(f"checkpoint {source} does not fit the model: " + "; ".join(problems))


def _checkpoint_paths(directory: pathlib.Path, checkpointer: ocp.PyTreeCheckpointer,
                      config: Pi0Config
                      ) -> tuple[dict[tuple[str, ...], tuple[str, ...]], list[tuple[str, ...]]]:
    """Checkpoint path -> model path of every array of the openpi params checkpoint `directory`,
    after checking its tree against `config`'s (only the orbax metadata is read), and the model
    paths of the LoRA adapters a base checkpoint lacks."""
    source = repr(str(directory))
    fix = ("point model.pretrained at an openpi params folder (e.g. <openpi checkpoint>/params, "
           "which holds _METADATA)")
    if not directory.is_dir():
        raise ValueError(f"model.pretrained: {source} is not a directory; {fix}")
    try:
        metadata = checkpointer.metadata(directory)
        tree = None if metadata is None or metadata.item_metadata is None \
            else metadata.item_metadata.tree
    except Exception as e:  # noqa: BLE001 - orbax raises many kinds on a folder of other files
        raise ValueError(f"model.pretrained: {source} is not a readable orbax checkpoint "
                         f"({type(e).__name__}: {str(e).splitlines()[0][:200]}); {fix}") from e
    if not tree:
        contents = sorted(p.name for p in directory.iterdir())[:5]
        raise ValueError(f"model.pretrained: {source} is not an orbax checkpoint (it holds "
                         f"{contents or 'nothing'}); {fix}")
    if set(tree) != {"params"}:
        raise ValueError(f"pretrained checkpoint {source} has top-level keys {sorted(tree)}; "
                         "an openpi params checkpoint has exactly ['params']")
    flat_meta = _flatten(tree)
    # NNX training checkpoints end every path in "value"; strip it only when all paths do.
    strip_value = all(p[-1] == "value" for p in flat_meta)
    # Checkpoint path -> model path: drop the "params" root (and the "value" level).
    to_model = {p: p[1:-1] if strip_value else p[1:] for p in flat_meta}
    expected = {p: leaf.shape for p, leaf in _flatten(param_shapes(config)).items()}
    found = {to_model[p]: leaf.shape for p, leaf in flat_meta.items()}
    missing = []
    if not any(is_adapter(p[-1]) for p in found):  # a base checkpoint: the adapters start anew
        missing = [p for p in expected if is_adapter(p[-1])]
        expected = {p: shape for p, shape in expected.items() if p not in missing}
    check_tree(found, expected, source)
    return to_model, missing


def check_pretrained(path: str | os.PathLike, config: Pi0Config) -> None:
    """Raises ValueError (naming the folder and the fix) unless `path` is an openpi params
    checkpoint that fits `config`; reads only its metadata."""
    with ocp.PyTreeCheckpointer() as checkpointer:
        _checkpoint_paths(pathlib.Path(path).expanduser().resolve(), checkpointer, config)


def load_pretrained(path: str | os.PathLike, config: Pi0Config, *,
                    shardings: Mapping[str, Any] | None = None, seed: int = 0) -> Params:
    """Restores an openpi params checkpoint whose tree equals `config`'s parameter tree.

    Args:
      path: the orbax directory (openpi's `.../params`).
      config: the preset the params must fit (names and shapes, exactly).
      shardings: optional tree of `jax.sharding.Sharding` like the params: restore each leaf as a
        jax.Array with that sharding (each process reads only its shards). Default: numpy arrays.
      seed: the init of LoRA adapters the checkpoint lacks.
    Returns:
      the nested params dict, float32 leaves.
    """
    directory = pathlib.Path(path).expanduser().resolve()
    with ocp.PyTreeCheckpointer() as checkpointer:
        to_model, missing = _checkpoint_paths(directory, checkpointer, config)
        flat_shardings = _flatten(shardings) if shardings is not None else {}

        def restore_args(p):
            if shardings is None:
                return ocp.RestoreArgs(restore_type=np.ndarray, dtype=np.float32)
            return ocp.ArrayRestoreArgs(restore_type=jax.Array, dtype=np.float32,
                                        sharding=flat_shardings[to_model[p]])

        args = _unflatten({p: restore_args(p) for p in to_model})
        restored = checkpointer.restore(directory, ocp.args.PyTreeRestore(restore_args=args))
    params = {to_model[p]: leaf for p, leaf in _flatten(restored).items()}
    if missing:  # the adapters of a base checkpoint, from their init
        def adapters(rng):
            flat = _flatten(init_params(config, rng))
            return {_SEP.join(p): flat[p] for p in missing}

        out_shardings = (None if shardings is None
                         else {_SEP.join(p): flat_shardings[p] for p in missing})
        initialized = jax.jit(adapters, out_shardings=out_shardings)(jax.random.key(seed))
        params.update({tuple(k.split(_SEP)): v if shardings is not None else np.asarray(v)
                       for k, v in initialized.items()})
    return _unflatten(params)
