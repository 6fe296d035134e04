#!/usr/bin/env bash
# Regenerate docs/benchmarks.md: run the benches (the full accuracy protocol with the example
# rooms' rigs, ≈ 15 minutes on 2 cores, the speed bench with live tracking, ≈ 8 minutes, and the
# eye pose bench three times, one worker per core (--jobs; times on 2 cores):
# 600 patient eyes with the radius fitted, each captured again moved (--displacement: what a
# check against a reference captured at set-up sees), ≈ 45 minutes (a patient eye takes two to
# three times the sharp eye's time to render), 200 with their biometry given (each patient's MRI
# as good or as bad as drawn), captured again moved, ≈ 15 minutes, and the old sharp-limbus eye
# on 600, ≈ 15 minutes), the reliability bench (kill -9, unplugged devices,
# a full disk, load and fuzz through daemons on loopback, a few minutes; its full-disk part needs
# root for its tmpfs and says skipped otherwise) and render their JSON.
# Figures and PNGs are kept in build/benchmarks/.
# Usage: bash scripts/benchmarks.sh [--quick | --accuracy | --speed | --reliability | --pose]
#                                   [--poses N]
#   --accuracy, --speed, --reliability, --pose: only that bench (the full accuracy protocol, ≈ 15
#   minutes, the speed bench, ≈ 8, the reliability bench, a few, or the eye pose bench's three
#   runs, ≈ 1.25 hours), its part of the page made anew and the rest left as it is (the accuracy
#   run's part: the page's head and its Accuracy section, the daily QA's figures with it; its
#   calibration in build/benchmarks/accuracy/ is the one later full runs, --speed and --pose
#   use: run --accuracy first on a fresh clone).
#   --poses N: N patient eyes (with --displacement) and N sharp eyes, N/3 with biometry, instead
#   of 600, 600 and 200 (the page names each run's count; its bootstrap intervals show the cost).
set -euo pipefail
cd "$(dirname "$0")/.."
mode=all
quick=()
poses=600
while [[ $# -gt 0 ]]; do
    case "$1" in
        --accuracy | --speed | --reliability | --pose) mode="${1#--}"; shift ;;
        --quick) quick=(--quick); shift ;;
        --poses) poses="$2"; shift 2 ;;
        *) echo "usage: bash scripts/benchmarks.sh [--quick | --accuracy | --speed |" \
                "--reliability | --pose] [--poses N]" >&2
           exit 2 ;;
    esac
done
bash scripts/setup.sh
out=build/benchmarks
mkdir -p "$out"
# The load's status readers are wrk (a client in C) when it is installed: a Python client on the
# same two cores measures mostly its own saturation.
if ! command -v wrk > /dev/null && [[ $(id -u) == 0 ]] && command -v apt-get > /dev/null; then
    apt-get install -y -q wrk > /dev/null || echo "wrk not installed: Python status readers" >&2
fi
splice_only() {
    # splice_only NAME COMMAND...: only that bench, its JSON in $out/NAME.json, and its part of
    # the page made anew (report.py --splice); a failed run or report leaves the page as it was.
    local name=$1
    shift
    "$@" > "$out/$name.json"
    .venv/bin/python -m eyeserver.bench.report --splice docs/benchmarks.md \
        "--$name" "$out/$name.json" > "$out/benchmarks.md"
    mv "$out/benchmarks.md" docs/benchmarks.md
    echo "docs/benchmarks.md: its $name part regenerated"
    exit 0
}
pose_runs() {
    # The eye pose bench's three runs, their JSON in $out/pose*.json, one worker per core.
    local jobs
    jobs=$(nproc)
    .venv/bin/eyeserver bench pose --json --poses "$poses" --displacement --jobs "$jobs" \
        --calibration "$out/accuracy/calibration" > "$out/pose.json"
    .venv/bin/eyeserver bench pose --json --poses "$((poses / 3))" --biometry --displacement \
        --jobs "$jobs" --calibration "$out/accuracy/calibration" > "$out/pose_biometry.json"
    .venv/bin/eyeserver bench pose --json --eyes sharp --poses "$poses" --jobs "$jobs" \
        --calibration "$out/accuracy/calibration" > "$out/pose_sharp.json"
}
case "$mode" in
    accuracy) splice_only accuracy .venv/bin/eyeserver bench accuracy --json \
        --out "$out/accuracy" ;;
    speed) splice_only speed .venv/bin/eyeserver bench speed --json \
        --calibration "$out/accuracy/calibration" ;;
    reliability) splice_only reliability .venv/bin/eyeserver bench reliability --json ;;
    pose)
        pose_runs
        .venv/bin/python -m eyeserver.bench.report --splice docs/benchmarks.md \
            --pose "$out/pose.json" --pose "$out/pose_biometry.json" \
            --pose "$out/pose_sharp.json" > "$out/benchmarks.md"
        mv "$out/benchmarks.md" docs/benchmarks.md
        echo "docs/benchmarks.md: its eye pose part regenerated"
        exit 0 ;;
esac
.venv/bin/eyeserver bench accuracy --json "${quick[@]}" --out "$out/accuracy" > "$out/accuracy.json"
.venv/bin/eyeserver bench speed --json --calibration "$out/accuracy/calibration" > "$out/speed.json"
pose_runs
.venv/bin/eyeserver bench reliability --json > "$out/reliability.json"
.venv/bin/python -m eyeserver.bench.report "$out/accuracy.json" "$out/speed.json" \
    "$out/pose.json" "$out/pose_biometry.json" "$out/pose_sharp.json" \
    --reliability "$out/reliability.json" > "$out/benchmarks.md"
mv "$out/benchmarks.md" docs/benchmarks.md  # a failed report leaves the page as it was
echo "docs/benchmarks.md regenerated (figures in $out/accuracy/)"
