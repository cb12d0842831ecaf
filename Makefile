# The two commands of the README: `make run` and `make test`. Each creates .venv when missing.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
ARGS   ?=

export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl
export RAY_USAGE_STATS_ENABLED ?= 0

.PHONY: run test install lint system-deps lock clean

# Headless MuJoCo rendering uses EGL on Mesa (llvmpipe, CPU only): Debian packages libegl1,
# libegl-mesa0 and libgl1-mesa-dri. Installed here when missing and we are root; otherwise
# the README says what to install. The PostgreSQL tests start a throw-away server from Debian's
# `postgresql` package (initdb, pg_ctl), installed the same way; without it they are skipped.
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing headless EGL (Mesa) for MuJoCo rendering"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null; \
	  else \
	    echo "warning: Mesa EGL not found; install libegl1 libegl-mesa0 libgl1-mesa-dri for the MuJoCo backend" >&2; \
	  fi; \
	fi
	@if ! ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing PostgreSQL (server for the PostgreSQL tests)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null; \
	  else \
	    echo "warning: PostgreSQL server not found; install postgresql to run the PostgreSQL tests" >&2; \
	  fi; \
	fi

# requirements.lock pins every package to the versions the test suite passed with (make lock).
$(STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c requirements.lock -e '.[test]'
	@touch $(STAMP)

install: system-deps $(STAMP)

run: system-deps $(STAMP)
	$(VENV)/bin/comexp $(ARGS)

test: system-deps $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

lock: $(STAMP)
	$(PY) -m pip freeze --exclude-editable | grep -v '^-e ' > requirements.lock

clean:
	rm -rf $(VENV) build *.egg-info
