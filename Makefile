# The two commands of the README: `make run` and `make test`. Each creates .venv when missing.
# `make run` installs what a job needs: comexp and its dependencies (no extras), plus Mesa EGL
# when ARGS choose the MuJoCo backend. `make test` (and `make install`) install every extra
# and the system packages the tests use (EGL, a PostgreSQL server).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
RUN_STAMP := $(VENV)/.installed-run
ARGS   ?=

# The extras of the development venv and of requirements.lock: every extra pyproject.toml
# declares (today `test`; an extra added later, e.g. `postgres`, is picked up by the next
# `make lock` and `make install` with no edit here), so the two can never disagree.
EXTRAS := $(shell $(PYTHON) -c 'import tomllib; print(",".join(sorted(tomllib.load(open("pyproject.toml", "rb"))["project"].get("optional-dependencies", {}))))')
# Not pinned in requirements.lock (tests/test_install.py reads this line): comexp itself, and the
# packaging tools that `python -m venv` seeds per Python version (3.11: pip and setuptools 65;
# 3.12: pip only). No pinned package needs them at run time; the build's setuptools comes from
# pyproject's [build-system] in pip's isolated build environment.
LOCK_EXCLUDE := comexp pip setuptools wheel
# setuptools prints an informational "Editable installation" warning for every editable install
# of a package-dir layout like ours (backends/, workers/, conf/ mapped into comexp): silenced.
NO_EDITABLE_NOTICE := PYTHONWARNINGS='ignore:Editable installation:UserWarning'

export RAY_USAGE_STATS_ENABLED ?= 0

.PHONY: run test install lint system-deps system-deps-egl system-deps-postgres lock clean

# Headless MuJoCo rendering uses EGL on Mesa (llvmpipe, CPU only): Debian packages libegl1,
# libegl-mesa0 and libgl1-mesa-dri. Installed here when missing and we are root; otherwise
# the README says what to install. The PostgreSQL tests start a throw-away server from Debian's
# `postgresql` package (initdb, pg_ctl), installed the same way; without it they are skipped.
# `make run` needs neither unless its ARGS choose backend=mujoco (EGL).
system-deps: system-deps-egl system-deps-postgres

system-deps-egl:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing headless EGL (Mesa) for MuJoCo rendering"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null; \
	  else \
	    echo "warning: Mesa EGL not found; install libegl1 libegl-mesa0 libgl1-mesa-dri for the MuJoCo backend" >&2; \
	  fi; \
	fi

system-deps-postgres:
	@if ! ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing PostgreSQL (server for the PostgreSQL tests)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null; \
	  else \
	    echo "warning: PostgreSQL server not found; install postgresql to run the PostgreSQL tests" >&2; \
	  fi; \
	fi

# The system packages `make run` needs for its ARGS: EGL for backend=mujoco, nothing else.
RUN_SYSTEM_DEPS := $(if $(findstring backend=mujoco,$(ARGS)),system-deps-egl)

# requirements.lock pins every installed package (make lock); tests/test_install.py fails when
# the venv and the lock differ.
$(STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	@echo "$(PY) -m pip install -q -c requirements.lock -e '.[$(EXTRAS)]'"
	@$(NO_EDITABLE_NOTICE) $(PY) -m pip install -q -c requirements.lock -e '.[$(EXTRAS)]'
	@touch $(STAMP) $(RUN_STAMP)

# What a job needs (the lock's versions, no extras); a full install (above) covers it too.
$(RUN_STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	@echo "$(PY) -m pip install -q -c requirements.lock -e ."
	@$(NO_EDITABLE_NOTICE) $(PY) -m pip install -q -c requirements.lock -e .
	@touch $(RUN_STAMP)

install: system-deps $(STAMP)

run: $(RUN_SYSTEM_DEPS) $(RUN_STAMP)
	$(VENV)/bin/comexp $(ARGS)

test: system-deps $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Reproducible: a fresh temporary venv gets the project with all its extras from pyproject's
# ranges alone (no constraints: the newest versions the index offers), and the lock is exactly
# what that venv holds. Rerun after any change to dependencies or extras, then `make install`.
lock:
	@set -e; tmp=$$(mktemp -d); trap 'rm -rf "$$tmp"' EXIT; \
	echo "make lock: fresh venv, pip install -e '.[$(EXTRAS)]' without constraints"; \
	$(PYTHON) -m venv "$$tmp/venv"; \
	"$$tmp/venv/bin/python" -m pip install -q --upgrade pip; \
	$(NO_EDITABLE_NOTICE) "$$tmp/venv/bin/python" -m pip install -q -e '.[$(EXTRAS)]'; \
	{ echo "# Generated by make lock: pip freeze of a fresh venv after pip install -e '.[$(EXTRAS)]'"; \
	  echo "# (pyproject.toml ranges, no constraints). Not listed: $(LOCK_EXCLUDE)."; \
	  "$$tmp/venv/bin/python" -m pip freeze --all $(addprefix --exclude ,$(LOCK_EXCLUDE)); \
	} > requirements.lock.tmp; \
	mv requirements.lock.tmp requirements.lock; \
	echo "requirements.lock: $$(grep -c '==' requirements.lock) packages"

clean:
	rm -rf $(VENV) build *.egg-info requirements.lock.tmp
