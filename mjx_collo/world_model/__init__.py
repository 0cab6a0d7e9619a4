"""Recurrent state-space world model (Dreamer v1 Gaussian / DreamerV2 categorical RSSM).

Pure functions over a parameter pytree; the flax modules live in :mod:`mjx_collo.nets`. Every
function takes the static :class:`~mjx_collo.config.WorldModelConfig` first; its float fields may
be JAX tracers inside a swept program, so nothing branches on them in Python.

One concept per module:

* :mod:`.rssm` — the RSSM state, its parameters (:func:`init`), filtering (:func:`obs_step`,
  :func:`observe`) and imagination (:func:`img_step`, :func:`imagine`, :func:`imagine_policy`);
* :mod:`.dists` — the stochastic state's distributions (Gaussian or categorical with unimix);
* :mod:`.heads` — observation encoder/decoder and the reward head (MSE or symlog two-hot);
* :mod:`.losses` — the ELBO with KL balancing, J_latent, and the update (:func:`train_step`);
* :mod:`.adapter` — the world model as the planners' :class:`LatentModel`
  (:func:`latent_model`) and as the Dreamer actor's imagination (:func:`imagination_model`).
"""

from mjx_collo.world_model.adapter import imagination_model, latent_model, plan_params
from mjx_collo.world_model.dists import (
    _noise,
    _sample,
    _stats,
    dist_mean,
    entropy,
    kl_div,
    log_prob,
)
from mjx_collo.world_model.heads import (
    PIXEL_NDIM,
    decode,
    encode,
    postprocess_obs,
    predict_obs,
    preprocess_obs,
    reward,
    reward_bins,
    reward_nll,
    symexp,
    symlog,
    twohot,
)
from mjx_collo.world_model.losses import (
    Batch,
    JLatentArgs,
    Posterior,
    init_opt_state,
    j_latent,
    kl_loss,
    loss,
    loss_scales,
    make_optimizer,
    train_step,
    value_and_grad,
)
from mjx_collo.world_model.rssm import (
    Params,
    RSSMState,
    feat_size,
    get_feat,
    imagine,
    imagine_policy,
    img_step,
    img_step_mean,
    init,
    initial_state,
    obs_step,
    observe,
    prior_mean,
    prior_stats,
    stoch_size,
)

__all__ = [
    "PIXEL_NDIM",
    "Batch",
    "JLatentArgs",
    "Params",
    "Posterior",
    "RSSMState",
    "_noise",
    "_sample",
    "_stats",
    "decode",
    "dist_mean",
    "encode",
    "entropy",
    "feat_size",
    "get_feat",
    "imagination_model",
    "imagine",
    "imagine_policy",
    "img_step",
    "img_step_mean",
    "init",
    "init_opt_state",
    "initial_state",
    "j_latent",
    "kl_div",
    "kl_loss",
    "latent_model",
    "log_prob",
    "loss",
    "loss_scales",
    "make_optimizer",
    "obs_step",
    "observe",
    "plan_params",
    "postprocess_obs",
    "predict_obs",
    "preprocess_obs",
    "prior_mean",
    "prior_stats",
    "reward",
    "reward_bins",
    "reward_nll",
    "stoch_size",
    "symexp",
    "symlog",
    "train_step",
    "twohot",
    "value_and_grad",
]
