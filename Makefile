# Fresh clone -> `make demo` or `make test`. Each target installs what it needs:
# `make demo` / `make install` the core only (what `crossfield` needs at run time),
# `make test` adds the test and basler extras, `make bench` the bench extra, each
# behind its own stamp, so that `make test` after `make demo` installs only the extras.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-core
STAMP_TEST  := $(VENV)/.installed-test
STAMP_BENCH := $(VENV)/.installed-bench
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# Debian packages the tests need: Mesa's lavapipe Vulkan driver, so the real
# Rerun viewer renders headless (screenshots, ViewerClient) with no GPU; chromium for
# the headless screenshot of report.html (tests/report/test_report_html_pictures.py); postgresql
# for the catalog's tests against a real server they start themselves (tests/catalog/conftest.py).
APT_PACKAGES := mesa-vulkan-drivers libvulkan1 chromium postgresql

.PHONY: demo test bench install apt-packages clean

# Editable install. setuptools says "Editable installation ... Please be careful
# with folders in your working directory with the same name as your package" after
# every editable install whose package-dir is not a plain src/flat layout (ours maps
# pipeline/ -> crossfield, on purpose: docs/python-api.md). That note is an
# InformationOnly warning, which setuptools documents as meant for warning
# filters; pip re-emits it as a UserWarning, filtered here by its exact text
# and nothing else (there is no crossfield/ folder to take precedence).
EDITABLE_NOTE := -W "ignore:Editable installation:UserWarning"

# pip's own output is kept (what it downloads and installs), each step announced first.
$(PY):
	@echo "creating $(VENV)/ (python -m venv) and upgrading pip ..."
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip

$(STAMP): pyproject.toml | $(PY)
	@echo "installing crossfield and its run-time dependencies into $(VENV)/ (pip install -e .) ..."
	$(PY) $(EDITABLE_NOTE) -m pip install -e .
	touch $(STAMP)

$(STAMP_TEST): pyproject.toml $(STAMP)
	@echo "adding the test and basler extras (pytest, hypothesis, pypylon) ..."
	$(PY) $(EDITABLE_NOTE) -m pip install -e '.[test,basler]'
	touch $(STAMP_TEST)

$(STAMP_BENCH): pyproject.toml $(STAMP_TEST)
	@echo "adding the bench extra (pytest-benchmark) ..."
	$(PY) $(EDITABLE_NOTE) -m pip install -e '.[test,bench]'
	touch $(STAMP_BENCH)

install: $(STAMP)

apt-packages:
	@dpkg -s $(APT_PACKAGES) >/dev/null 2>&1 || { \
	  $(SUDO) apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q --no-install-recommends $(APT_PACKAGES); }

demo: $(STAMP)
	$(VENV)/bin/crossfield run --scenario table3

# One BLAS thread: on a shared 2-core machine OpenBLAS's own threads make the
# calibration solves 20-30x slower (measured: 2.56 s against 0.13 s).
test bench: export OPENBLAS_NUM_THREADS = 1

test: $(STAMP_TEST) apt-packages
	$(PY) -m pytest -q

bench: $(STAMP_BENCH)
	$(PY) bench/run.py

clean:
	rm -rf $(VENV) build *.egg-info
