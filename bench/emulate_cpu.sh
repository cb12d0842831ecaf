#!/usr/bin/env bash
# Run a command as if on another x86-64 CPU: the libraries that pick SIMD kernels at run time
# are told to skip the newer ones, so floating point takes the paths another machine takes.
#
#   bench/emulate_cpu.sh avx2 .venv/bin/python -m pytest -q tests/test_episode.py
#   bench/emulate_cpu.sh sse               # no command: print what each library now uses
#
# Profiles
#   native  nothing changed
#   avx2    an AVX2 + FMA machine without AVX-512 (e.g. AMD Zen 2/3, Intel Haswell-Comet Lake)
#   sse     the x86-64-v2 baseline: no AVX, no FMA (Nehalem class)
#
# What is switched (each library's own documented control):
#   numpy     NPY_DISABLE_CPU_FEATURES (its dispatch groups X86_V3 = AVX2/FMA, X86_V4 = AVX-512)
#   OpenBLAS  OPENBLAS_CORETYPE (numpy's and scipy's BLAS/LAPACK: matmul, lstsq, solve, eigh)
#   OpenCV    OPENCV_CPU_DISABLE, and cv2.setUseOptimized(False) for sse (via sitecustomize)
#   glibc     GLIBC_TUNABLES=glibc.cpu.hwcaps (libm's FMA/AVX2 variants of exp, sin, pow...,
#             used by Python's math module and the physics engines)
# Not switchable: code compiled for one fixed instruction set (MuJoCo, pybullet, GEOS) takes
# the same path on every x86-64 CPU, except through libm.
set -euo pipefail

profile=${1:-}
[ $# -gt 0 ] && shift

case "$profile" in
native) ;;
avx2)
	export NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR"
	export OPENBLAS_CORETYPE=Haswell
	export OPENCV_CPU_DISABLE=AVX512-SKX
	export GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX512F,-AVX512DQ,-AVX512VL,-AVX512BW,-AVX512CD
	;;
sse)
	export NPY_DISABLE_CPU_FEATURES="X86_V3 X86_V4 AVX512_ICL AVX512_SPR"
	export OPENBLAS_CORETYPE=Nehalem
	export OPENCV_CPU_DISABLE=AVX512-SKX,AVX2,FMA3,FP16,AVX,POPCNT,SSE4.2,SSE4.1
	export GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA,-AVX,-AVX512F,-AVX512DQ,-AVX512VL,-AVX512BW,-AVX512CD
	site=$(mktemp -d)
	trap 'rm -rf "$site"' EXIT
	printf 'import cv2\ncv2.setUseOptimized(False)\n' >"$site/sitecustomize.py"
	export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
	;;
*)
	echo "usage: bench/emulate_cpu.sh native|avx2|sse [command...]" >&2
	exit 2
	;;
esac

if [ $# -eq 0 ]; then
	py=${PYTHON:-.venv/bin/python}
	OPENBLAS_VERBOSE=2 "$py" - <<'EOF'
import cv2
import numpy as np
from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

np.linalg.solve(np.eye(3), np.ones(3))  # OpenBLAS prints "Core: ..." on first use
print("numpy dispatch targets in use:", [f for f in __cpu_dispatch__ if __cpu_features__.get(f)])
print("OpenCV:", cv2.getCPUFeaturesLine(), "(? = disabled), optimized:", cv2.useOptimized())
EOF
	/lib64/ld-linux-x86-64.so.2 --list-diagnostics 2>/dev/null | grep '^dl_platform' || true
	exit 0
fi
# sse needs the trap to clean up, so no exec
"$@"
