"""What a saved :class:`~harness.sb3.dqn.DoubleDQN` model states about itself: its layout
(:data:`MODEL_FORMAT`), read before SB3 loads it (:func:`check_model_format`), and the compact
form of a model kept only to be played (:func:`target_as_online`)."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import torch as th

__all__ = [
    "FORMAT_KEY",
    "MODEL_FORMAT",
    "OldModelError",
    "check_model_format",
    "saved_model_format",
    "target_as_online",
]

#: The layout of the models :class:`DoubleDQN` saves, stored in each (``harness_model_format`` in
#: its ``data``). Increased when a saved model's layout changes; an older model is refused, not
#: read through shims. 2: the classes under
#: ``harness.sb3``, the target network always stored (a compact export stores it as the online
#: network's tensors, once), an action mask in the env's dtype, no retired settings.
MODEL_FORMAT = 2
#: The ``data`` key that holds a saved model's :data:`MODEL_FORMAT`.
FORMAT_KEY = "harness_model_format"


class OldModelError(ValueError):
    """A saved model in another layout than :data:`MODEL_FORMAT` (one line)."""


def saved_model_format(path: str | Path | io.BufferedIOBase) -> int | None:
    """The :data:`MODEL_FORMAT` a saved model zip states, 1 for a DQN model saved before
    formats were stated, ``None`` for anything else: not a model zip, or another algorithm's
    (left to SB3 to report)."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None
    finally:
        if isinstance(path, io.BufferedIOBase):
            path.seek(0)
    if not isinstance(data, dict):
        return None
    if FORMAT_KEY in data:
        return int(data[FORMAT_KEY])
    # Only a DQN model (SB3's or this harness's) can be an older harness model.
    return 1 if "target_update_interval" in data else None


def target_as_online(policy_state: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
    """A DQN policy's ``state_dict`` whose target network entries (``q_net_target.*``) are the
    online network's tensors (``q_net.*``), the same objects, so that ``torch.save`` stores them
    once: the compact form of a model kept only to be played (``harness export``)."""
    online = {k: v for k, v in policy_state.items() if not k.startswith("q_net_target.")}
    target = {
        "q_net_target." + k.removeprefix("q_net."): v
        for k, v in online.items()
        if k.startswith("q_net.")
    }
    return {**online, **target}


def check_model_format(path: str | Path | io.BufferedIOBase) -> None:
    """Refuse a saved model in another layout than :data:`MODEL_FORMAT`.

    Raises:
        OldModelError: The model was saved in an older or newer layout (one line).
    """
    found = saved_model_format(path)
    where = path if isinstance(path, (str, Path)) else "the model"
    if found is not None and found < MODEL_FORMAT:
        raise OldModelError(
            f"{where}: saved by an older version of the harness (model format {found}, this "
            f"version reads {MODEL_FORMAT}); retrain it with this version"
        )
    if found is not None and found > MODEL_FORMAT:
        raise OldModelError(
            f"{where}: saved by a newer version of the harness (model format {found}, this "
            f"version reads {MODEL_FORMAT}); update the harness to load it"
        )
