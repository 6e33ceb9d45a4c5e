#!/usr/bin/env bash
# Every run behind docs/results.md, then the report: the default CPU suite (44 min on 2 cores
# at 3375dac), Table 2 on shepp, shell and bone, Table 3 and the views sweep on shell, training
# seeds 1 and 2 of r2 and gr on shepp, needles, shell, shells and bone (hours in all).
# One run at a time with both cores (--jobs 1): measured at 3375dac, a 64^3 gr / r2 run alone
# takes 200 s on cement where two side by side with one thread each took 582-588 s.
# Finished runs are skipped, so a rerun only does what is missing or stale.
#   bash experiments/run_cpu.sh [OUT] [extra experiment options, e.g. --dry-run]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/cpu
if [[ $# -gt 0 && $1 != -* ]]; then OUT=$1; shift; fi
SUITE=experiments/suite_cpu.json
MI_GRG=${MI_GRG:-.venv/bin/mi-grg}
J=(--jobs 1)
case " $* " in *" --dask"* | *" --jobs"*) J=() ;; esac   # a cluster, or your own count
"$MI_GRG" experiment all    --suite "$SUITE" --out "$OUT" "${J[@]}" "$@"
"$MI_GRG" experiment table2 --suite "$SUITE" --out "$OUT" --cases shepp,shell,bone "${J[@]}" "$@"
"$MI_GRG" experiment table3 --suite "$SUITE" --out "$OUT" --cases shell "${J[@]}" "$@"
"$MI_GRG" experiment views  --suite "$SUITE" --out "$OUT" --cases shell "${J[@]}" "$@"
"$MI_GRG" experiment seeds  --suite "$SUITE" --out "$OUT" --cases shepp,needles,shell,shells,bone "${J[@]}" "$@"
case " $* " in
  *" --dry-run "*) ;;
  *) "$MI_GRG" report --out "$OUT" --report docs/results.md --record docs/cpu/runs ;;
esac
