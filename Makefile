# mjx_collo — every target sets itself up: a fresh clone needs only `make train ENV=cheetah` or `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
# GPU=1 also installs jax's CUDA plugin matching the pinned jax (the `gpu` extra of pyproject.toml).
GPU    ?= 0
comma  := ,
EXTRAS := test$(if $(filter 1,$(GPU)),$(comma)gpu)
STAMP  := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))

ENV     ?= cheetah
METHOD  ?= collodreamer
SEEDS   ?= 1
STEPS   ?=
RUN     ?=
ARGS    ?=
SWEEP   ?=
CKPT    ?=
RUNS    ?=
OUT     ?=
EPISODES ?= 10
VIDEO   ?= 0
STUDY   ?= smoke
PYTEST_ARGS ?=
# pytest-xdist workers: the suite is mostly single-threaded XLA compiles, so 2 workers on 2 cores
# cut a cold `make test` from ~14.9 to ~10.6 min.
TEST_WORKERS ?= 2

# Quiet noisy deprecation chatter from dependencies.
export PYTHONWARNINGS ?= ignore::DeprecationWarning

# preview: our frames beside MuJoCo's render of the same states (ENV=<task> or ENV=all), in preview/.
.PHONY: gl preview bench-render install train sweep eval combine study report test test-all lint format bench bench-envs bench-model bench-planner bench-plan-quality bench-conv clean

install: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[$(EXTRAS)]'
	@touch $(STAMP)

train: install
	$(PY) train.py --env $(ENV) --method $(METHOD) --seeds $(SEEDS) \
	  $(if $(STEPS),--steps $(STEPS)) $(if $(RUN),--run $(RUN)) $(ARGS)

sweep: install
	$(PY) train.py --env $(ENV) --method $(METHOD) --seeds $(SEEDS) \
	  $(if $(STEPS),--steps $(STEPS)) $(if $(RUN),--run $(RUN)) \
	  $(if $(SWEEP),--sweep "$(SWEEP)") $(ARGS)

eval: install
	$(PY) evaluate.py --ckpt $(CKPT) --episodes $(EPISODES) $(if $(filter 1,$(VIDEO)),--video) $(ARGS)

# Seeds trained in separate runs as one curve + summary.json: make combine RUNS="dir1 dir2" OUT=dir
combine: install
	$(PY) -m mjx_collo.combine $(RUNS) --out $(OUT) $(ARGS)

# A study: the cells of configs/study/$(STUDY).yaml one after another (re-run to resume), then its
# report. RUN= moves the run directories (default runs/study/$(STUDY)).
study: install
	$(PY) study.py run $(STUDY) $(if $(RUN),--root $(RUN)) $(ARGS)

report: install
	$(PY) study.py report $(STUDY) $(ARGS)

# MuJoCo's own renderer, the reference the render tests and `make preview` compare our frames with,
# needs OpenGL without a screen: Debian's libosmesa6. Best effort: where it cannot be installed
# (not root, no apt), those checks skip and say why.
gl:
	@ldconfig -p 2>/dev/null | grep -q libOSMesa || { command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] \
	  && { apt-get install -y -qq libosmesa6 >/dev/null 2>&1 || { apt-get update -qq && apt-get install -y -qq libosmesa6 >/dev/null; }; } \
	  || echo "note: libosmesa6 not installed; checks against MuJoCo's renderer will skip"; }

preview: install gl
	MUJOCO_GL=$${MUJOCO_GL:-osmesa} $(PY) -m envs.reference $(ENV) --out preview $(ARGS)

# The CI suite: everything not marked slow (~9 min warm, ~11-15 min cold on 2 cores: docs/OPERATIONS.md).
test: install gl
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup -m "not slow" $(PYTEST_ARGS)

# Everything, including the statistical env-parity, learning and multi-process tests.
test-all: install gl
	MJX_COLLO_TEST_FULL_OPT=1 $(PY) -m pytest -q $(PYTEST_ARGS)

lint: install
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

format: install
	$(PY) -m ruff format .
	$(PY) -m ruff check --fix .

bench-envs: install
	$(PY) benchmarks/bench_envs.py $(ARGS)

bench-model: install
	$(PY) benchmarks/bench_model.py $(ARGS)

bench-render: install
	$(PY) benchmarks/bench_render.py $(ARGS)

bench-planner: install
	$(PY) benchmarks/bench_planner.py $(ARGS)

# Pixel world model: ms per conv layer, forward + backward, as the training loop runs it.
bench-conv: install
	$(PY) benchmarks/bench_conv.py $(ARGS)

# Planner defaults are judged here: a trained cheetah model (benchmarks/fixtures), real returns.
bench-plan-quality: install
	$(PY) benchmarks/bench_plan_quality.py $(ARGS)

bench: install
	$(PY) benchmarks/bench_train.py $(ARGS)

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
