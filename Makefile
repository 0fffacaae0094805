# pano-pipe: `make demo` and `make test` are all a fresh machine needs.
SHELL := /bin/bash
PY := .venv/bin/python
PIP := .venv/bin/pip
BIN := .venv/bin
# what the pipeline needs (make demo), and what the tests add on top (make test)
STAMP := .venv/.installed
TEST_STAMP := .venv/.installed-test
DEMO_SCENE := scenes/demo
TORCH := torch==2.13.0
# the SOG check's third-party reader (npm; optional, see setup-test)
SPLAT_TRANSFORM := @playcanvas/splat-transform@2.7.1
# auto: the CUDA build of torch where nvidia-smi lists a GPU, the CPU build elsewhere (scripts/install_torch.sh)
TORCH_BUILD ?= auto
export TORCH_BUILD
# Debian packages: open3d needs libusb and libgomp; the report test uses chromium.
APT_REQUIRED := libusb-1.0-0 libgomp1
APT_OPTIONAL := chromium

.PHONY: setup setup-test demo test bench gpu-check clean-venv system-deps

setup: $(STAMP)

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	@test -x $(PY) || python3 -m venv .venv
	$(PIP) install -q --upgrade pip
	@# torch first and pinned, CPU or CUDA build by what the machine has (TORCH_BUILD=auto|cpu|cuda)
	TORCH="$(TORCH)" PIP=$(PIP) PY=$(PY) scripts/install_torch.sh
	$(PIP) install -q -e .
	@# LPIPS's linear heads ship in the lpips wheel; --no-deps: its torchvision would replace our torch.
	$(PIP) install -q --no-deps lpips==0.1.4
	@touch $(STAMP)

# the test extras (pytest, hypothesis, xdist, ray, ...): only `make test` needs them
setup-test: $(TEST_STAMP)

$(TEST_STAMP): $(STAMP)
	@# the CPU build's triton is the one CI runs the GPU kernels with in its interpreter; a CUDA build brings its own
	$(PIP) install -q -e ".[test$$(grep -qx cpu .venv/.torch-build && echo ,interpreter)]"
	@# optional: PlayCanvas's splat-transform, the third-party SOG reader of tests/export (into .venv/node)
	@if command -v npm >/dev/null 2>&1; then npm install -s --prefix .venv/node --no-audit --no-fund $(SPLAT_TRANSFORM) \
	  >/dev/null 2>&1 || echo "note: $(SPLAT_TRANSFORM) not installed (the SOG reader check will skip)"; \
	  else echo "note: no npm: $(SPLAT_TRANSFORM) not installed (the SOG reader check will skip)"; fi
	@touch $(TEST_STAMP)

system-deps:
	@missing=""; for p in $(APT_REQUIRED); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	opt=""; for p in $(APT_OPTIONAL); do dpkg -s $$p >/dev/null 2>&1 || opt="$$opt $$p"; done; \
	if [ -n "$$missing$$opt" ]; then \
	  SUDO=$$( [ "$$(id -u)" = 0 ] && echo "" || echo sudo ); \
	  echo "installing Debian packages:$$missing$$opt"; \
	  $$SUDO apt-get update -qq >/dev/null || true; \
	  if [ -n "$$missing" ]; then $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; fi; \
	  if [ -n "$$opt" ]; then $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$opt >/dev/null \
	    || echo "note: optional$$opt not installed (the report's browser test will skip)"; fi; \
	fi

demo: setup
	$(BIN)/pano-pipe simulate $(DEMO_SCENE) --preset demo --with-layout --with-depth
	$(BIN)/pano-pipe run all $(DEMO_SCENE)
	$(BIN)/pano-pipe report $(DEMO_SCENE)

test: setup-test
	$(PY) -m pytest -q -n 2 --dist loadfile --durations=15

bench: setup
	$(BIN)/pano-pipe bench render --out docs
	$(BIN)/pano-pipe simulate /tmp/pano-bench-sim --height 512 --views 4 --test-views 0 --effects all --profile
	$(BIN)/pano-pipe simulate /tmp/pano-bench-sim --height 512 --views 4 --test-views 0 --effects none --profile
	$(BIN)/pano-pipe bench pipeline --out docs
	$(BIN)/pano-pipe bench batch --out docs

# on a GPU machine: the CUDA tests with compiled kernels and both GPU benches -> docs/gpu_check/ (docs/gpu.md)
gpu-check:
	scripts/gpu_check.sh

clean-venv:
	rm -rf .venv
