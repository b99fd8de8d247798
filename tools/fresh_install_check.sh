#!/usr/bin/env bash
# Run the README's commands as a newcomer would: a new virtual environment, the newest
# versions that pyproject.toml's bounds allow, a clean copy of the committed tree (HEAD).
#
#   tools/fresh_install_check.sh            the test command: pip install -e ".[test]" && python -m pytest
#   tools/fresh_install_check.sh --smoke    then the install command with the smoke study (~15 min)
#   tools/fresh_install_check.sh --main     then the first command as written (all default studies, ~1 h)
#
# Prints the versions it installed and keeps everything in the folder it names at the start.
set -euo pipefail

mode=${1:-}
case "$mode" in ""|--smoke|--main) ;; *) echo "usage: $0 [--smoke|--main]" >&2; exit 2 ;; esac
repo=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d "${TMPDIR:-/tmp}/ema_uq_fresh.XXXXXX")
echo "fresh install check of $(git -C "$repo" rev-parse --short HEAD) in $work"

unset PYTHONPATH                     # nothing but the fresh environment may be imported
python3 -m venv "$work/venv"
# shellcheck disable=SC1091
source "$work/venv/bin/activate"
mkdir "$work/src"
git -C "$repo" archive HEAD | tar -x -C "$work/src"
cd "$work/src"
python -m pip install --quiet --upgrade pip

step() { echo "== $* ($(date +%T))"; }
step 'pip install -e ".[test]"'
pip install --quiet -e ".[test]"
pip list --format=freeze > "$work/versions.txt"
python --version
grep -iE '^(pytest|numpy|scipy|numba|xarray|arviz|emcee|salib|matplotlib|snakemake|pandas|tqdm)==' "$work/versions.txt"

step "python -m pytest"
start=$SECONDS
set +e
python -m pytest -q -p no:cacheprovider --durations=15 2>&1 | tee "$work/pytest.log" | tail -40
status=${PIPESTATUS[0]}
set -e
echo "test suite: exit $status, $((SECONDS - start)) s wall"
[ "$status" -eq 0 ] || exit "$status"

if [ -n "$mode" ]; then
    step "pip install -e . && snakemake --cores all ${mode#--}"
    pip install --quiet -e .
    start=$SECONDS
    if [ "$mode" = --smoke ]; then
        snakemake --cores all --config 'studies=[smoke]' > "$work/snakemake.log" 2>&1
    else
        snakemake --cores all > "$work/snakemake.log" 2>&1
    fi
    echo "workflow: exit 0, $((SECONDS - start)) s wall; reports: $(ls reports/*.html)"
fi
echo "fresh install check passed"
