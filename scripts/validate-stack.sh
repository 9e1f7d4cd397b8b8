#!/usr/bin/env bash
# Score a deploy stack on the validation worlds only, before anyone looks at an issue's bars:
#   bash scripts/validate-stack.sh AGENT [OUT_DIR]
# e.g. bash scripts/validate-stack.sh policies/namo-robust+rescue+shield+scan-match /tmp/val-nrsm
#
# The sets (the validation sets of docs/results/2026-11-27-namo-robust), 11 runs of `curlnav eval`:
#   e90 r90 h90 e91 r91 h91  the NAMO office, indoor and auditorium floors at seeds 90 and 91 under
#                            exact (e), realistic (r) and harsh (h) senses, 10 pairs x 2 ball placements
#   sA sAr                   slam-office, slam-floor, slam-namo-indoor at seed 90, exact and realistic
#   sB sBr                   slam-namo-auditorium, slam-namo-office, barn-3x3 at seed 90, exact and realistic
#   tmaze-p4                 the T-Maze's hardest pair (a training world: a stack that blocks its tight gap fails here)
# 620 trials; two runs at a time on a 2-core machine, about 10 minutes. Seeds 90-99 are held out of
# training (docs/guide/curricula.md); the bars' seeds (300, the real suite) are never used here.
# Prints a table of successes and base contact events per trial per set, and the total, and writes
# it to OUT_DIR/validation.txt beside each run's CSVs.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 1 ] || [ $# -gt 2 ]; then
    echo "usage: bash scripts/validate-stack.sh AGENT [OUT_DIR]" >&2
    exit 2
fi
agent=$1
out=${2:-$(mktemp -d /tmp/validate-stack.XXXX)}
mkdir -p "$out"
curlnav=${CURLNAV:-.venv/bin/curlnav}
namo="--world namo-office:SEED --world namo-indoor:SEED --world namo-auditorium:SEED --pairs 10 --seeds 2"
slam_a="--world slam-office:90 --world slam-floor:90 --world slam-namo-indoor:90 --pairs 10 --seeds 2"
slam_b="--world slam-namo-auditorium:90 --world slam-namo-office:90 --world barn-3x3:90 --pairs 10 --seeds 2"
declare -A sets=(
    [e90]="${namo//SEED/90}" [r90]="${namo//SEED/90} --sensor-noise realistic" [h90]="${namo//SEED/90} --sensor-noise harsh"
    [e91]="${namo//SEED/91}" [r91]="${namo//SEED/91} --sensor-noise realistic" [h91]="${namo//SEED/91} --sensor-noise harsh"
    [sA]="$slam_a" [sAr]="$slam_a --sensor-noise realistic"
    [sB]="$slam_b" [sBr]="$slam_b --sensor-noise realistic"
    [tmaze-p4]="--world scheduler/curricula/worlds/t-maze-0.yaml --pair p4 --episodes 20"
)
order=(e90 r90 h90 e91 r91 h91 sA sB sAr sBr tmaze-p4)

run_set() {  # one set: its CSVs and log under $out/NAME
    local name=$1
    # shellcheck disable=SC2086  # the set's options are words
    if ! "$curlnav" eval "$agent" ${sets[$name]} --jobs 1 --out "$out/$name" > "$out/$name.log" 2>&1; then
        echo "[validate] $name failed: see $out/$name.log" >&2
        return 1
    fi
    echo "[validate] $name done ($(date +%H:%M:%S))" >&2
}

echo "[validate] $agent on ${#order[@]} validation sets, two at a time; logs and CSVs in $out" >&2
failed=0
for ((i = 0; i < ${#order[@]}; i += 2)); do
    pids=()
    for name in "${order[@]:i:2}"; do
        run_set "$name" & pids+=($!)
    done
    for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
done
[ "$failed" = 0 ] || { echo "[validate] a set failed: no total" >&2; exit 1; }

"${curlnav%curlnav}python" - "$out" "${order[@]}" <<'EOF' | tee "$out/validation.txt"
import csv, sys
out, names = sys.argv[1], sys.argv[2:]
total = trials = 0
print(f"{'set':<9} {'successes':>12} {'contact events/trial':>21}")
for name in names:
    with open(f"{out}/{name}/summary.csv") as f:
        rows = list(csv.DictReader(f))
    row = next((r for r in rows if r["world"] == "all"), rows[-1])  # one world: its own row
    n = int(row["episodes"]); won = round(float(row["success_rate"]) * n)
    total, trials = total + won, trials + n
    print(f"{name:<9} {won:>5} of {n:<4} {float(row['base_collision_events_per_trial']):>21.2f}")
print(f"{'all':<9} {total:>5} of {trials:<4}")
EOF
