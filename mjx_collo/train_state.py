"""What one seed's run carries between iterations and chunks (a pytree of arrays).

Everything a run needs to continue bit for bit lives here, so a checkpoint is this pytree and
nothing else; with several seeds every leaf gets a leading seed axis.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax
import optax
from flax import struct

from mjx_collo.actor import ActorState
from mjx_collo.agent import AgentCarry
from mjx_collo.replay import ReplayState
from mjx_collo.value import ValueState
from mjx_collo.world_model import Params as WorldModelParams

if TYPE_CHECKING:  # brax's env state; imported for the annotation only (brax pulls in mujoco.mjx)
    from brax.envs.base import State as EnvState


@struct.dataclass
class TrainState:
    """One seed's state.

    Learning: ``wm`` / ``wm_opt`` the world model and its optimizer state (over the flat parameter
    vector); ``value`` the value network and its target (None when ``value.enabled`` is false);
    ``actor`` the Dreamer actor (None for planners); ``wm_old`` the frozen world model of J_latent
    (None when it is off); ``lam_ema`` an EMA of the planner's mean dynamics multiplier, which
    sets J_latent's weight.

    Acting: ``env`` the MJX env states of the ``num_envs`` envs; ``agent`` their posterior and
    action caches; ``ep_return`` [E] the running return of each env's current episode; ``replay``
    the on-device replay.

    Bookkeeping: ``key`` this seed's RNG; ``hyper`` {dotted key: []} the swept float
    hyperparameters of this seed; ``updates`` world-model updates done; ``nonfinite_streak`` /
    ``nonfinite_total`` updates skipped for a non-finite loss or gradient, in a row and in all.

    ``explorer``: the disagreement ensemble (:class:`mjx_collo.explorer.ExplorerState`) when
    ``explore.disag.heads`` > 0, else None (last, with a default, so runs without one keep the
    structure of their checkpoints).
    """

    wm: WorldModelParams
    wm_opt: optax.OptState
    value: ValueState | None
    actor: ActorState | None
    wm_old: WorldModelParams | None
    env: EnvState
    agent: AgentCarry
    replay: ReplayState
    key: jax.Array
    hyper: dict[str, jax.Array]
    ep_return: jax.Array
    updates: jax.Array
    nonfinite_streak: jax.Array
    nonfinite_total: jax.Array
    lam_ema: jax.Array
    explorer: Any = None
