#!/usr/bin/env bash
# The runs behind the H100 tables of docs/benchmarks.md, in one call on a GPU machine:
#   ONESHOT_JAX_COMMIT=<commit> bash benchmarks/gpu/h100.sh [OUTDIR]
# from the repository root of a clean tree of <commit> (the commit is recorded as given when
# the tree has no git metadata). Each stage writes its JSON after every cell, so a stage cut
# by its time limit keeps the cells it finished. Print the tables with `--render` (see the
# docs page).
set -u
out=${1:-benchmarks/gpu}
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c "import jax, oneshot_jax; print(jax.__version__, jax.devices(), oneshot_jax.__version__)" || exit 1
timeout 300 python3 benchmarks/parallel.py --nx 2 4 8 16 --horizons 1000 10000 100000 \
    --fit-T 10000 --memory --json "$out/h100_grid.json"
timeout 120 python3 benchmarks/parallel.py --nx 2 8 16 --horizons 64 128 256 512 --no-fit \
    --json "$out/h100_short.json"
timeout 150 python3 benchmarks/fit_strategy.py --nx 2 --horizons 1000 10000 100000 --repeats 2 \
    --json "$out/h100_fit_nx2.json"
