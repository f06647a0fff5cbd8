# Two entry points for a fresh machine: `make demo` and `make test`.
# Both create .venv and install matscan into it. torch is pinned to the CPU build
# first, so nothing pulls a CUDA torch.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO := demo

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml Makefile
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check torch==2.13.0
	@# one OpenCV only: the contrib build (it has the ColorChecker detector) replaces the plain one,
	@# whose files it shares, so a venv that has the plain one loses both before the install
	@if $(BIN)/pip show opencv-python-headless >/dev/null 2>&1; then \
		$(BIN)/pip uninstall --quiet --yes opencv-python-headless opencv-contrib-python-headless; fi
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/matscan reconstruct @sample --out $(DEMO)/reconstruction --overwrite --validate 4
	$(BIN)/matscan sheet @sample --maps $(DEMO)/reconstruction --out $(DEMO)/contact_sheet.png
	@echo "demo: open $(DEMO)/reconstruction/report.html and $(DEMO)/contact_sheet.png"

test: $(STAMP)
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null || \
		{ echo "installing Debian's chromium for the report test"; \
		  (apt-get update -qq && apt-get install -y -qq chromium) >/dev/null 2>&1 || \
		  echo "chromium could not be installed: the browser test will be skipped"; }
	@test -d $(VENV)/node/node_modules/gltf-validator || ! command -v npm >/dev/null || \
		{ echo "installing the Khronos glTF validator (npm gltf-validator) for the export test"; \
		  npm install --prefix $(VENV)/node --no-audit --no-fund --silent gltf-validator >/dev/null 2>&1 || \
		  echo "gltf-validator could not be installed: the validator test will be skipped"; }
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check matscan tests bench tools
	$(BIN)/ruff format --check matscan tests bench tools

bench: $(STAMP)
	$(BIN)/python bench/render.py

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
