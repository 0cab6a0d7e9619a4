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


def _filled(rows: int, steps: int, num_envs: int = 2) -> replay.ReplayState:
    state = replay.init(_cfg(capacity=2 * rows * num_envs), num_envs, 2, _fields())
    add = jax.jit(replay.add)
    for t in range(steps):
        state = add(state, _row(t, num_envs, first=t % 4 == 0))
    return state


def test_run_rows_counts_the_first_observation_and_each_reset():
    # 3 episodes of 4 agent steps: 1 first row + 12 steps + 3 first rows after the ends
    assert replay.run_rows(12, 4) == 16
    assert replay.run_rows(13, 4) == 17
    cfg = _cfg(capacity=400)  # 400 env steps / repeat 2 / 2 envs = 100 rows per env
    assert replay.rows_per_env(cfg, 2, 2) == 100
    assert replay.rows_per_env(cfg, 2, 2, run=40) == 40  # a shorter run: only what it writes
    assert replay.rows_per_env(cfg, 2, 2, run=1000) == 100  # a longer one: the capacity (a ring)
    assert replay.rows_per_env(cfg, 2, 2, run=1) == cfg.length  # never below one window


def test_a_grown_or_shrunk_buffer_that_never_wrapped_samples_the_same_windows():
    """An extended run grows its buffer (checkpoint restore): the same rows where they were, so
    every sample and every later write is what a buffer of the larger size gives."""
    small, large = _filled(12, 9), _filled(30, 9)
    grown = replay.resize(small, 30)
    for k in large.data:
        np.testing.assert_array_equal(np.asarray(grown.data[k]), np.asarray(large.data[k]))
    assert int(grown.pos) == int(large.pos) == 9 and int(grown.count) == 9
    key = jax.random.PRNGKey(3)
    a, b = replay.sample(grown, key, 8, 3), replay.sample(large, key, 8, 3)
    for k in a:
        np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]))
    shrunk = replay.resize(large, 10)  # an old checkpoint's capacity-sized buffer, cut to the run
    for k in shrunk.data:
        np.testing.assert_array_equal(np.asarray(shrunk.data[k]), np.asarray(large.data[k][:10]))
    after_a = replay.add(shrunk, _row(9, 2))
    after_b = replay.add(large, _row(9, 2))
    np.testing.assert_array_equal(
        np.asarray(after_a.data["obs"][:10]), np.asarray(after_b.data["obs"][:10])
    )


def test_resizing_a_wrapped_buffer_keeps_the_newest_rows_in_time_order():
    state = _filled(5, 8)  # rows 0..7 written into 5: rows 3..7 remain, the oldest (3) at pos 3
    assert int(state.pos) == 3
    grown = replay.resize(state, 7)
    obs_t = np.asarray(grown.data["obs"][:, 0, 0])
    np.testing.assert_array_equal(obs_t, [3, 4, 5, 6, 7, 0, 0])
    assert int(grown.pos) == 5 and int(grown.count) == 5
    shrunk = replay.resize(state, 3)
    np.testing.assert_array_equal(np.asarray(shrunk.data["obs"][:, 0, 0]), [5, 6, 7])
    assert int(shrunk.pos) == 0 and int(shrunk.count) == 3
    np.testing.assert_array_equal(np.asarray(shrunk.data["is_first"][:, 0]), [False, False, False])
    first = np.asarray(grown.data["is_first"][:, 0])
    np.testing.assert_array_equal(first, [False, True] + [False] * 5)
