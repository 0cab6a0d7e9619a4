"""Typed configuration tree: YAML defaults + task/method overlays + dotted CLI overrides.

Validation is done by pydantic (frozen, ``extra="forbid"`` models): unknown keys and wrong types are
errors that name the key and the valid choices. Models are frozen and hashable, so a config can be
closed over or passed as a static argument to ``jax.jit``.

Swept float hyperparameters (``SWEEP="value.gamma=0.9,0.99"``) are not static: inside the compiled
program :func:`with_values` returns a copy of the config whose swept leaves are traced arrays, so
library code reads ``cfg.value.gamma`` either way and never branches on float values in Python.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
FORMAT_VERSION = 1


class ConfigError(ValueError):
    """A one-line, user-facing configuration problem (unknown key, bad type, missing preset)."""


class Section(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)


# --------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------


class EnvConfig(Section):
    task: str
    action_repeat: int
    episode_env_steps: int
    physics: Literal["tuned", "dmc"]
    obs: Literal["state", "pixels"]


Positive = Annotated[int, Field(gt=0)]
NonNegative = Annotated[int, Field(ge=0)]


class RunConfig(Section):
    steps: Positive
    num_envs: Positive
    prefill: NonNegative
    train_every: Positive
    train_steps: NonNegative
    pretrain: NonNegative
    eval_every: Positive
    eval_episodes: Positive
    chunk_env_steps: Positive
    checkpoint_every: Positive
    keep_checkpoints: Positive
    save_replay: bool
    max_nonfinite: Positive
    seed: int
    eval_overlap: bool


class ReplayConfig(Section):
    capacity: Positive
    batch: Positive
    length: Positive


class OptimConfig(Section):
    lr: float
    eps: float
    clip: float
    weight_decay: float


class KLConfig(Section):
    balance: float
    free: float
    scale: float


class LossScales(Section):
    obs: float
    reward: float
    kl: float


class WorldModelConfig(Section):
    latent: Literal["gaussian", "categorical"]
    deter: int
    hidden: int
    stoch: int
    classes: int
    min_std: float
    unimix: float
    gru_layernorm: bool
    act: Literal["elu", "silu", "relu", "tanh"]
    units: int
    enc_layers: int
    dec_layers: int
    reward_layers: int
    reward_head: Literal["mse", "twohot"]
    reward_bins: int
    symlog_obs: bool
    cnn_depth: int
    decode_every: Positive
    kl: KLConfig
    loss_scales: LossScales
    optim: OptimConfig


class ValueTargetConfig(Section):
    kind: Literal["hard", "ema"]
    every: int
    tau: float


class ValueConfig(Section):
    enabled: bool
    layers: int
    units: int
    gamma: float
    lam: float
    mode: Literal["replay", "plan_final", "plan_inner"]
    v_every: int
    target: ValueTargetConfig
    bootstrap: bool
    residual_scale: float | Literal["auto"]
    clip: bool
    clip_range: tuple[float, float]
    dropout: Annotated[float, Field(ge=0.0, lt=1.0)]
    norm: Literal["none", "layer", "batch"]
    optim: OptimConfig


class ShootingConfig(Section):
    init_std: float
    samples: int
    elites: int
    iters: int
    temperature: float
    min_std: float
    max_std: float
    warm_start: bool
    color: Annotated[float, Field(ge=0.0)]
    color_frac: Annotated[float, Field(ge=0.0, le=1.0)]


class InitCEMConfig(Section):
    samples: int
    elites: int
    iters: int
    std: float
    color: Annotated[float, Field(ge=0.0)]
    color_frac: Annotated[float, Field(ge=0.0, le=1.0)]
    prior_frac: Annotated[float, Field(ge=0.0, le=1.0)]


class PlannerConfig(Section):
    kind: Literal["latco", "collodreamer", "cem", "mppi", "mppi_value", "dreamer"]
    solver: Literal["gauss_newton", "cg", "adam"]
    space: Literal["full", "reduced"]
    horizon: int
    mpc_steps: int
    iters: int
    init_lam: float
    init_nu: float
    dyn_eps: float
    act_eps: float
    lm_alpha: float
    lm_eta: float
    lam_clip: tuple[float, float]
    dyn_scale: float
    act_scale: float
    init_weight: float
    gn_damping: float
    step_control: Literal["none", "lm"]
    cg_iters: int
    adam_lr: float
    adam_decay: float
    adam_b2: float
    refine_iters: int
    refine_lr: float
    gamma: float
    value_lambda: Annotated[float, Field(ge=0.0, le=1.0)]
    warm_start: bool
    init: Literal["rollout", "random", "cem", "policy", "policy_cem"]
    init_std: float
    init_cem: InitCEMConfig
    shooting: ShootingConfig


class ActorConfig(Section):
    layers: int
    units: int
    horizon: int
    init_std: float
    min_std: float
    mean_scale: float
    entropy: float
    pg: float
    bc: float
    starts: int
    optim: OptimConfig


class DisagConfig(Section):
    heads: Annotated[int, Field(ge=0)]
    layers: Annotated[int, Field(ge=0)]
    units: Annotated[int, Field(ge=1)]
    lr: Annotated[float, Field(gt=0.0)]
    scale: Annotated[float, Field(ge=0.0)]


class ExploreConfig(Section):
    noise: Annotated[float, Field(ge=0.0)]
    color: Annotated[float, Field(ge=0.0)]
    disag: DisagConfig


class JLatentConfig(Section):
    enabled: bool
    beta0: float
    ratio_clip: float
    log_ratio_clip: float
    old_every: int


class Config(Section):
    method: Literal["collodreamer", "latco", "dreamer", "cem", "mppi", "mppi_value"]
    env: EnvConfig
    run: RunConfig
    replay: ReplayConfig
    wm: WorldModelConfig
    value: ValueConfig
    planner: PlannerConfig
    actor: ActorConfig
    explore: ExploreConfig
    j_latent: JLatentConfig
    version: int


# --------------------------------------------------------------------------------------------
# Loading: defaults.yaml -> method overlay -> task overlay -> presets -> dotted overrides
# --------------------------------------------------------------------------------------------


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML loader that refuses a key given twice in one mapping: PyYAML would keep the last
    silently, so a second ``planner:`` block in an overlay would drop the first one's settings."""

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # `<<: *anchor` merges a mapping; keys given beside it override it
            key = self.construct_object(key_node, deep=deep)
            line = key_node.start_mark.line + 1
            try:
                hash(key)
            except TypeError:
                raise ConfigError(
                    f"{key_node.start_mark.name}: line {line}: a mapping key must be a plain value"
                ) from None
            if key in seen:
                raise ConfigError(
                    f"{key_node.start_mark.name}: key '{key}' appears twice in one mapping (lines "
                    f"{seen[key]} and {line}); merge them into one"
                )
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping from ``path``; bad YAML or a repeated key is one :class:`ConfigError` line."""
    with open(path) as f:
        try:
            data = yaml.load(f, Loader=_UniqueKeyLoader) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {str(e).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at top level, got {type(data).__name__}")
    return data


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Recursively merge ``over`` into a copy of ``base`` (mappings merge, other values replace)."""
    out = copy.deepcopy(dict(base))
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _valid_keys(model: type[BaseModel], path: Sequence[str]) -> list[str]:
    """Field names of the section at ``path`` (for 'valid keys are ...' messages)."""
    cls: Any = model
    for p in path:
        field = cls.model_fields.get(p)
        if field is None or not (
            isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)
        ):
            return []
        cls = field.annotation
    return sorted(cls.model_fields)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"a.b=1e-3"`` -> (["a", "b"], 0.001). Values are parsed as YAML scalars/lists."""
    if "=" not in text:
        raise ConfigError(f"bad override {text!r}: expected key=value, e.g. wm.deter=300")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not p for p in key.split(".")):
        raise ConfigError(f"bad override {text!r}: empty key component")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as e:
        raise ConfigError(f"bad override {text!r}: value is not valid YAML ({e})") from None
    return key.split("."), value


def _set_path(tree: dict[str, Any], path: Sequence[str], value: Any) -> None:
    node = tree
    for p in path[:-1]:
        nxt = node.get(p)
        if not isinstance(nxt, dict):
            nxt = {}
            node[p] = nxt
        node = nxt
    node[path[-1]] = value


def _format_error(err: ValidationError) -> str:
    parts = []
    for e in err.errors():
        loc = [str(x) for x in e["loc"]]
        key = ".".join(loc)
        if e["type"] == "extra_forbidden":
            valid = _valid_keys(Config, loc[:-1])
            hint = f"; valid keys in {'.'.join(loc[:-1]) or 'the top level'}: {', '.join(valid)}"
            parts.append(f"unknown config key '{key}'{hint}")
        else:
            given = e.get("input")
            parts.append(f"bad value for '{key}' ({given!r}): {e['msg']}")
    return "; ".join(parts)


def available_presets(kind: str) -> list[str]:
    """Names of the YAML overlays in ``configs/<kind>/``."""
    return sorted(p.stem for p in (CONFIG_DIR / kind).glob("*.yaml"))


def _overlay(kind: str, name: str, required: bool) -> dict[str, Any]:
    path = CONFIG_DIR / kind / f"{name}.yaml"
    if not path.exists():
        if required:
            raise ConfigError(
                f"unknown {kind} preset '{name}'; available: {', '.join(available_presets(kind))}"
            )
        return {}
    return read_yaml(path)


# Keys added after FORMAT_VERSION 1 was written, with the value that reproduces how configs
# without them behaved. A checkpoint's stored config is completed with these before validation, so
# older runs still evaluate and resume (under a default that differs, resuming names the change).
ADDED_KEYS: dict[str, Any] = {
    "planner.refine_iters": 0,
    "planner.refine_lr": 0.05,
    "planner.init_cem": {"samples": 100, "elites": 10, "iters": 4, "std": 1.0},
    "planner.value_lambda": 1.0,
    "run.eval_overlap": False,
    "wm.reward_head": "mse",
    "wm.reward_bins": 255,
    "actor.pg": 1.0,
    "actor.bc": 0.0,
    "actor.starts": 0,
    "env.obs": "state",
    "planner.init_cem.color": 0.0,
    "planner.shooting.color": 0.0,
    "explore.color": 0.0,
    "planner.init_cem.color_frac": 1.0,
    "planner.shooting.color_frac": 1.0,
    "planner.init_cem.prior_frac": 1.0,
    "explore.disag": {"heads": 0, "layers": 2, "units": 128, "lr": 3.0e-4, "scale": 1.0},
    "wm.decode_every": 1,
}


def complete_saved(tree: Mapping[str, Any]) -> dict[str, Any]:
    """A stored config tree with :data:`ADDED_KEYS` filled in where it lacks them."""
    out = deep_merge({}, tree)
    for dotted, value in ADDED_KEYS.items():
        path = dotted.split(".")
        node: Any = out
        for p in path[:-1]:
            node = node.get(p) if isinstance(node, dict) else None
        if isinstance(node, dict) and path[-1] not in node:
            node[path[-1]] = copy.deepcopy(value)  # later entries may fill in its keys
    return out


def build(tree: Mapping[str, Any]) -> Config:
    """Validate a plain nested dict into a :class:`Config` (raises :class:`ConfigError`)."""
    try:
        return Config.model_validate(dict(tree))
    except ValidationError as e:
        raise ConfigError(_format_error(e)) from None


def load(
    task: str | None = None,
    method: str | None = None,
    presets: Sequence[str] = (),
    overrides: Sequence[str] = (),
) -> Config:
    """Resolve the layered config.

    Args:
      task: canonical task name (e.g. ``cheetah_run``); its overlay ``configs/task/<task>.yaml`` is
        applied if present.
      method: one of the ``configs/method/*.yaml`` presets; None: defaults.yaml's ``method``
        (collodreamer), whose overlay applies as well, so that ``load()`` is the default agent.
      presets: extra overlays from ``configs/preset/`` (e.g. ``debug``), applied in order.
      overrides: dotted ``key=value`` strings, applied last.
    """
    tree = read_yaml(CONFIG_DIR / "defaults.yaml")
    method = method if method is not None else tree.get("method", "collodreamer")
    tree = deep_merge(tree, _overlay("method", method, required=True))
    tree["method"] = method
    if task is not None:
        tree = deep_merge(tree, _overlay("task", task, required=False))
        _set_path(tree, ["env", "task"], task)
    for p in presets:
        tree = deep_merge(tree, _overlay("preset", p, required=True))
    return build(apply_overrides(tree, overrides))


def apply_overrides(
    tree: dict[str, Any], overrides: Sequence[str], sections: Sequence[str] | None = None
) -> dict[str, Any]:
    """Set dotted ``key=value`` overrides in a plain config tree (in place; returned).

    With ``sections`` only keys under those top-level sections may be set (evaluation may change
    how a trained agent plans, not what it is).
    """
    for text in overrides:
        path, value = parse_override(text)
        if sections is not None and path[0] not in sections:
            raise ConfigError(
                f"cannot override '{'.'.join(path)}' here: only "
                f"{', '.join(s + '.*' for s in sections)} keys may change; "
                "the rest must match the checkpoint"
            )
        _set_path(tree, path, value)
    return tree


def to_dict(cfg: Config) -> dict[str, Any]:
    return cfg.model_dump(mode="json")


def dump_yaml(cfg: Config, path: str | Path) -> None:
    """Write atomically (a temporary file renamed): a run stopped mid-write leaves no torn file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    tmp.replace(path)


PRIOR_KEYS = ("actor.pg", "actor.bc", "actor.starts")
# how the disagreement ensemble trains and weighs: inert without one (explore.disag.heads 0)
DISAG_KEYS = (
    "explore.disag.layers",
    "explore.disag.units",
    "explore.disag.lr",
    "explore.disag.scale",
)


def _flat_uses_prior(flat: Mapping[str, Any]) -> bool:
    return flat.get("planner.kind") != "dreamer" and flat.get("planner.init") in (
        "policy",
        "policy_cem",
    )


def inert_keys(flat: Mapping[str, Any]) -> set[str]:
    """Keys of a flattened config that cannot change its run, given its other values: the conv
    encoder's ``wm.cnn_depth`` in a run that sees states, and how the policy prior trains
    (:data:`PRIOR_KEYS`) in a run without one. A default changed for pixel runs, or for the
    prior, then leaves the other runs resumable and combinable with runs written before it."""
    pixel_only = {"wm.cnn_depth", "wm.decode_every"}
    inert = pixel_only if flat.get("env.obs", "state") == "state" else set()
    if not _flat_uses_prior(flat):
        inert |= set(PRIOR_KEYS)
    if not flat.get("explore.disag.heads", 0):
        inert |= set(DISAG_KEYS)
    return inert


def check_explore(cfg: Config) -> None:
    """The disagreement bonus's requirements (``explore.disag.heads`` > 0), checked on the config
    alone: it is a planner's reward term, its ensemble predicts state vectors, and the bonus
    enters the plans that act, not plans made inside value learning. Raises ConfigError."""
    if not cfg.explore.disag.heads:
        return
    if cfg.planner.kind == "dreamer":
        raise ConfigError(
            "explore.disag.heads > 0 adds a curiosity bonus to a planner's reward; "
            "planner.kind=dreamer acts from its actor (use a planner, or explore.disag.heads=0)"
        )
    if cfg.env.obs != "state":
        raise ConfigError(
            f"explore.disag.heads > 0 predicts the next state vector; env.obs={cfg.env.obs} "
            "has none (use env.obs=state, or explore.disag.heads=0)"
        )
    if cfg.value.enabled and cfg.value.mode == "plan_inner":
        raise ConfigError(
            "explore.disag.heads > 0 with value.mode=plan_inner would train the value on plans "
            "scored with the curiosity bonus; use value.mode=replay or plan_final"
        )


def check_prior(cfg: Config) -> None:
    """A policy prior's requirements, checked on the config alone (before anything compiles):
    it starts a collocation plan and learns from the value's returns. Raises ConfigError."""
    if uses_prior(cfg):
        # planner.COLLOCATION, spelled out: config imports nothing of the library
        if cfg.planner.kind not in ("latco", "collodreamer"):
            raise ConfigError(
                f"planner.init={cfg.planner.init} starts a collocation plan from the policy "
                f"prior; planner.kind={cfg.planner.kind} has no collocation plan (use latco or "
                "collodreamer, or planner.init=cem)"
            )
        if not cfg.value.enabled:
            raise ConfigError(
                f"planner.init={cfg.planner.init} trains its policy prior on the value's returns: "
                "it needs value.enabled=true (or plan without the prior: planner.init=cem)"
            )
        if cfg.actor.starts < 0:
            raise ConfigError(
                f"actor.starts={cfg.actor.starts}: the prior's imagination starts per update must "
                "be >= 0 (0: every replay posterior)"
            )
    elif cfg.actor.pg != 1.0 or cfg.actor.bc != 0.0:
        # actor.starts is not checked: the default ColloDreamer sets it (32), and
        # `planner.init=cem` on top of that default must run as the planner alone.
        raise ConfigError(
            "actor.pg and actor.bc set how the policy prior trains, and this run has "
            f"no prior (planner.init={cfg.planner.init}): set planner.init=policy or policy_cem, "
            "or leave actor.pg=1.0 actor.bc=0.0"
        )


def diff(a: Config, b: Config) -> list[str]:
    """Human-readable list of ``key: a -> b`` differences between two configs (keys inert in
    both, :func:`inert_keys`, are not differences)."""
    fa, fb = flatten(to_dict(a)), flatten(to_dict(b))
    inert = inert_keys(fa) & inert_keys(fb)
    keys = sorted((set(fa) | set(fb)) - inert)
    return [f"{k}: {fa.get(k)!r} -> {fb.get(k)!r}" for k in keys if fa.get(k) != fb.get(k)]


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


# --------------------------------------------------------------------------------------------
# Swept float hyperparameters
# --------------------------------------------------------------------------------------------


def uses_prior(cfg: Config) -> bool:
    """Whether the planner starts from a learned policy prior (``planner.init: policy`` or
    ``policy_cem``): an actor network trained beside the world model (docs/ALGORITHM.md §4.10)."""
    return _flat_uses_prior({"planner.kind": cfg.planner.kind, "planner.init": cfg.planner.init})


# Float keys a one-compile sweep cannot vary: they decide the program's shapes or state.
# explore.color > 0 keeps each env's noise sequence for the episode in the acting state; a
# planner's color_frac splits its samples into a white and a colored block of fixed sizes.
STATIC_FLOATS = {
    "explore.color",
    "planner.init_cem.color_frac",
    "planner.init_cem.prior_frac",
    "planner.shooting.color_frac",
}


def float_keys(cfg: Config) -> list[str]:
    """Dotted paths of every float leaf (the keys a sweep may vary within one compile), less the
    policy prior's objective weights when the run has no prior (they would change nothing)."""
    unused = set() if uses_prior(cfg) else set(PRIOR_KEYS)
    if not cfg.explore.disag.heads:
        unused |= set(DISAG_KEYS)
    return sorted(
        k
        for k, v in flatten(to_dict(cfg)).items()
        if isinstance(v, float) and k not in unused | STATIC_FLOATS
    )


def parse_sweep(text: str, cfg: Config) -> dict[str, list[float]]:
    """``"value.gamma=0.9,0.99;wm.optim.lr=3e-4,6e-4"`` -> {key: [values]} (validated).

    Separate items form a grid (every combination). Keys joined by ``+`` are tied: they take the
    same values together, one axis of the grid (``value.gamma+planner.gamma=0.9,0.99``: the
    value's discount and the planner's, varied as one discount)."""
    out: dict[str, list[float]] = {}
    valid = float_keys(cfg)
    for item in filter(None, (s.strip() for s in text.replace(";", " ").split())):
        if "=" not in item:
            raise ConfigError(f"bad sweep {item!r}: expected key=v1,v2,...")
        key, vals = item.split("=", 1)
        for part in key.split("+"):
            if part in STATIC_FLOATS:
                raise ConfigError(
                    f"cannot sweep '{part}' in one compile: it decides what the acting state "
                    "holds; run one value per run (or one study variant each)"
                )
            if part not in valid:
                raise ConfigError(
                    f"cannot sweep '{part}': only float hyperparameters can be swept in one "
                    f"compile; choose from: {', '.join(valid)}"
                )
        seen = [p for k in out for p in k.split("+")]
        if any(part in seen for part in key.split("+")):
            raise ConfigError(f"sweep key '{key}' repeats a key already swept")
        try:
            out[key] = [float(v) for v in vals.split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"bad sweep values for '{key}': {vals!r} are not floats") from None
        if not out[key]:
            raise ConfigError(f"sweep '{key}' has no values")
    pc = cfg.planner
    swept = [p for k in out for p in k.split("+")]
    if "planner.value_lambda" in swept and pc.kind in ("latco", "collodreamer"):
        if pc.solver != "adam":
            raise ConfigError(
                f"cannot sweep planner.value_lambda with planner.solver={pc.solver}: a swept "
                "lambda is a lambda-return over the plan, which needs planner.solver=adam (the "
                f"{pc.solver} residuals bootstrap the value at the plan's end only)"
            )
    return out


def with_values(cfg: Config, values: Mapping[str, Any]) -> Config:
    """Copy of ``cfg`` with dotted float leaves replaced (by floats or traced arrays).

    No validation is run, so JAX tracers may be inserted; shapes and other static fields stay.
    """
    if not values:
        return cfg
    grouped: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    for key, v in values.items():
        head, _, rest = key.partition(".")
        if rest:
            grouped.setdefault(head, {})[rest] = v
        else:
            direct[head] = v
    update = dict(direct)
    for head, sub in grouped.items():
        child = getattr(cfg, head)
        if not isinstance(child, BaseModel):
            raise ConfigError(f"'{head}' is not a config section")
        update[head] = with_values(child, sub)  # type: ignore[arg-type]
    return cfg.model_copy(update=update)


@functools.cache
def defaults() -> Config:
    return load()
