#!/usr/bin/env bash
# Every run behind docs/results.md, then the report: the default CPU suite (about 50 min on
# 2 cores), Table 2 on shepp, shell and bone, Table 3 and the views sweep on shell (about 60 min
# more), training seeds 1 and 2 of r2 and gr on shepp, needles, shell, shells and bone (59 min).
# Finished runs are skipped, so a rerun only does what is missing or stale.
#   bash experiments/run_cpu.sh [OUT] [extra experiment options, e.g. --dry-run]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/cpu
if [[ $# -gt 0 && $1 != -* ]]; then OUT=$1; shift; fi
SUITE=experiments/suite_cpu.json
MI_GRG=${MI_GRG:-.venv/bin/mi-grg}
"$MI_GRG" experiment all    --suite "$SUITE" --out "$OUT" "$@"
"$MI_GRG" experiment table2 --suite "$SUITE" --out "$OUT" --cases shepp,shell,bone "$@"
"$MI_GRG" experiment table3 --suite "$SUITE" --out "$OUT" --cases shell "$@"
"$MI_GRG" experiment views  --suite "$SUITE" --out "$OUT" --cases shell "$@"
"$MI_GRG" experiment seeds  --suite "$SUITE" --out "$OUT" --cases shepp,needles,shell,shells,bone "$@"
case " $* " in
  *" --dry-run "*) ;;
  *) "$MI_GRG" report --out "$OUT" --report docs/results.md ;;
esac
