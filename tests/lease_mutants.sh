#!/bin/bash
# Does the lease simulation judge? Each deliberate fault in turn: patch the rule, run
# tests/tests/lease_sim.rs on its 10 000 seeds, print the first failing seed and why, put
# the file back (git checkout: run it on a clean tree). About 10 minutes on 2 cores.
# Figures: docs/results-one-controller.md.
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/mfc-zenoh/target}"
files="plant-agent/src/lease.rs controller-service/src/replication.rs controller-service/src/lease.rs"
# shellcheck disable=SC2086
if ! git diff --quiet -- $files; then
  echo "lease_mutants: $files must have no uncommitted changes (each is put back with git checkout)" >&2
  exit 1
fi
run() {
  name="$1"; file="$2"; from="$3"; to="$4"
  python3 - "$file" "$from" "$to" <<'PY' || { echo "$name: PATTERN NOT FOUND"; return; }
import sys
p,a,b=sys.argv[1:]
t=open(p).read()
assert t.count(a)==1, (p,a,t.count(a))
open(p,'w').write(t.replace(a,b))
PY
  start=$(date +%s)
  # One thread, the 10 000 seeds only (not SOAK_FOUND): the first failing seed is the
  # lowest of them.
  out=$(MFC_LEASE_THREADS=1 cargo test -p system-tests --test lease_sim --locked -- one_holder 2>&1)
  git checkout -q "$file"
  seed=$(echo "$out" | grep -o "MFC_LEASE_SEED=[0-9]*" | head -1)
  why=$(echo "$out" | grep -m1 -A2 "panicked at" | tail -2 | tr '\n' ' ' | cut -c1-300)
  res=$(echo "$out" | grep -m1 "test result")
  echo "$name | $seed | $(( $(date +%s) - start )) s | $res | $why"
}
run "non-holder's command accepted" plant-agent/src/lease.rs "            Some(_) => Err(Fence::NotHolder)," "            Some(_) => Ok(Pass::Holder),"
run "epoch check skipped" plant-agent/src/lease.rs "            Some(h) if same(h) => Err(Fence::StaleEpoch)," "            Some(h) if same(h) => Ok(Pass::Holder),"
run "run check removed" plant-agent/src/lease.rs "        if c.run_id != self.run_id {
            return Err(Fence::OtherRun);
        }" ""
run "lapse removed" plant-agent/src/lease.rs "        if let Some(holder) = self.holder.take() {" "        if let Some(holder) = None::<String> {"
run "acknowledged before its partners hold it" controller-service/src/replication.rs "            _ => missing.push(p)," "            _ => held.push(p),"
run "a state that never claimed commands under its process's lease" controller-service/src/lease.rs "        if !self.claimed && self.holder == Holder::Me {" "        if false && !self.claimed && self.holder == Holder::Me {"
git status --short
