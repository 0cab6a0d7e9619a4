"""On-device replay: hand-built data, wrap-around, is_first, dtypes, memory accounting."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_collo import config, replay


def _cfg(capacity: int, length: int = 3, batch: int = 4) -> config.ReplayConfig:
    return config.load(
        presets=["debug"],
        overrides=[
            f"replay.capacity={capacity}",
            f"replay.length={length}",
            f"replay.batch={batch}",
        ],
    ).replay


def _fields() -> dict[str, jax.ShapeDtypeStruct]:
    return replay.default_fields((2,), 1)


def _row(t: int, num_envs: int, first: bool = False) -> dict[str, jnp.ndarray]:
    """Row t for every env: obs = [t, env], action = t, reward = 10 t + env."""
    env = jnp.arange(num_envs, dtype=jnp.float32)
    return {
        "obs": jnp.stack([jnp.full((num_envs,), float(t)), env], -1),
        "action": jnp.full((num_envs, 1), float(t)),
        "reward": 10.0 * t + env,
        "is_first": jnp.full((num_envs,), first),
    }


def test_init_sizes_dtypes_and_memory():
    fields = replay.default_fields((64, 64, 3), 6, obs_dtype=jnp.uint8)
    state = replay.init(_cfg(capacity=400), num_envs=2, action_repeat=2, fields=fields)
    # 400 env steps / repeat 2 / 2 envs = 100 rows per env.
    assert state.data["obs"].shape == (100, 2, 64, 64, 3)
    assert state.data["obs"].dtype == jnp.uint8
    assert state.data["action"].shape == (100, 2, 6)
    assert state.data["reward"].dtype == jnp.float32
    assert state.data["is_first"].dtype == jnp.bool_
    expected = 100 * 2 * (64 * 64 * 3 * 1 + 6 * 4 + 4 + 1)
    assert replay.memory_bytes(state) == expected
    abstract = jax.eval_shape(lambda: replay.init(_cfg(400), 2, 2, fields))
    assert replay.memory_bytes(abstract) == expected
    text = replay.describe(state)
    assert "100 rows x 2 envs" in text and "uint8[64, 64, 3]" in text and "MiB" in text
    with pytest.raises(ValueError, match="replay.length"):
        replay.init(_cfg(capacity=8, length=5), num_envs=2, action_repeat=2, fields=fields)


def test_add_wraps_around_and_casts():
    state = replay.init(_cfg(capacity=20), num_envs=2, action_repeat=2, fields=_fields())
    assert replay.capacity_rows(state) == 5
    add = jax.jit(replay.add)
    for t in range(7):
        state = add(state, _row(t, 2))
    assert int(state.pos) == 2 and int(state.count) == 5
    np.testing.assert_array_equal(state.data["obs"][:, 0, 0], [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(state.data["obs"][:, 1, 1], [1, 1, 1, 1, 1])
    np.testing.assert_array_equal(state.data["reward"][:, 1], [51, 61, 21, 31, 41])
    with pytest.raises(KeyError):
        replay.add(state, {"obs": jnp.zeros((2, 2))})


def test_can_sample_needs_a_full_window():
    state = replay.init(_cfg(capacity=20, length=3), 1, 2, _fields())
    for t in range(3):
        assert not bool(replay.can_sample(state, 3))
        state = replay.add(state, _row(t, 1))
    assert bool(replay.can_sample(state, 3))


@pytest.mark.parametrize("n_add", [4, 13])  # before and after wrap-around (S = 6)
def test_sample_windows_are_contiguous_and_never_cross_the_seam(n_add):
    length, rows, num_envs = 3, 6, 2
    state = replay.init(_cfg(capacity=2 * rows * num_envs, length=length), num_envs, 2, _fields())
    for t in range(n_add):
        state = replay.add(state, _row(t, num_envs))
    out = jax.jit(replay.sample, static_argnums=(2, 3))(state, jax.random.key(1), 512, length)
    t_seq = np.asarray(out["obs"][..., 0])
    env_seq = np.asarray(out["obs"][..., 1])
    assert out["obs"].shape == (512, length, 2) and out["is_first"].shape == (512, length)
    # Consecutive time steps of one env, all from the rows still stored.
    np.testing.assert_array_equal(np.diff(t_seq, axis=1), 1)
    assert (env_seq == env_seq[:, :1]).all()
    oldest = max(0, n_add - rows)
    assert t_seq.min() >= oldest and t_seq.max() <= n_add - 1
    # Every valid start and both envs are drawn (uniform sampling over windows).
    assert set(t_seq[:, 0]) == set(range(oldest, n_add - length + 1))
    assert set(env_seq[:, 0]) == {0, 1}
    # Rows stay aligned across fields.
    np.testing.assert_array_equal(out["action"][..., 0], t_seq)
    np.testing.assert_array_equal(out["reward"], 10 * t_seq + env_seq)


def test_is_first_marks_resets_inside_sequences():
    # Episodes of 4 rows: is_first at t = 0, 4, 8, ...; S = 10 so the buffer wraps.
    state = replay.init(_cfg(capacity=20, length=5), 1, 2, _fields())
    for t in range(23):
        state = replay.add(state, _row(t, 1, first=(t % 4 == 0)))
    out = replay.sample(state, jax.random.key(0), 256, 5)
    t_seq = np.asarray(out["obs"][..., 0]).astype(int)
    np.testing.assert_array_equal(np.asarray(out["is_first"]), t_seq % 4 == 0)
    assert np.asarray(out["is_first"])[:, 1:].any()  # resets do occur mid-sequence


def test_uint8_round_trip_and_vmap_over_seeds():
    fields = replay.default_fields((4, 4, 3), 2, obs_dtype=jnp.uint8)
    cfg = _cfg(capacity=40, length=2)

    def fill(key):
        state = replay.init(cfg, 2, 2, fields)
        obs = jax.random.randint(key, (5, 2, 4, 4, 3), 0, 256).astype(jnp.float32)

        def body(s, o):
            row = {
                "obs": o,
                "action": jnp.zeros((2, 2)),
                "reward": jnp.zeros(2),
                "is_first": jnp.zeros(2, bool),
            }
            return replay.add(s, row), None

        state, _ = jax.lax.scan(body, state, obs)
        return state, obs

    states, obs = jax.vmap(fill)(jax.random.split(jax.random.key(0), 2))
    assert states.data["obs"].dtype == jnp.uint8
    np.testing.assert_array_equal(states.data["obs"][:, :5], obs.astype(np.uint8))
    assert not np.array_equal(states.data["obs"][0], states.data["obs"][1])
    out = jax.vmap(lambda s, k: replay.sample(s, k, 3, 2))(
        states, jax.random.split(jax.random.key(1), 2)
    )
    assert out["obs"].shape == (2, 3, 2, 4, 4, 3) and out["obs"].dtype == jnp.uint8
