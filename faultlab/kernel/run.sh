#!/usr/bin/env bash
# Optional kernel suite: the loop through the kernel's own network stack. Two network
# namespaces joined by a veth pair (the project's own test hosts, on this machine only),
# the controller service in one, the plant agent in the other, and iptables dropping a
# share of the plant's packets at random (-m statistic). This kernel has no netem, so
# latency stays the user-space relay's job; loss is the kernel's here.
#
# Needs root and iproute2; installs iptables if missing; skips (exit 0) when it cannot run.
# Usage: bash faultlab/kernel/run.sh [LOSS]   (default 0.10)
set -euo pipefail
cd "$(dirname "$0")/../.."
LOSS=${1:-0.10}
skip() { echo "kernel suite: skipped ($1)"; exit 0; }
[ "$(id -u)" = 0 ] || skip "needs root"
command -v ip >/dev/null || skip "no iproute2"
if ! command -v iptables >/dev/null; then
  (apt-get update -qq && apt-get install -y -qq iptables) >/dev/null 2>&1 || skip "cannot install iptables"
fi
ip netns add mfc-probe 2>/dev/null || skip "cannot create network namespaces here"
ip netns del mfc-probe

TARGET=${CARGO_TARGET_DIR:-target}
# The debug build is the one the tests already made; a 10 s run does not need more.
cargo build -q -p controller-service -p plant-agent -p mfc-lab
BIN="$TARGET/debug"
WORK=$(mktemp -d)
cleanup() {
  [ -n "${SVC:-}" ] && kill "$SVC" 2>/dev/null || true
  ip netns del mfc-ctl 2>/dev/null || true
  ip netns del mfc-plant 2>/dev/null || true
  rm -rf "$WORK"
}
trap cleanup EXIT

ip netns add mfc-ctl
ip netns add mfc-plant
ip link add mfc-veth-c type veth peer name mfc-veth-p
ip link set mfc-veth-c netns mfc-ctl
ip link set mfc-veth-p netns mfc-plant
ip -n mfc-ctl addr add 10.77.0.1/24 dev mfc-veth-c
ip -n mfc-plant addr add 10.77.0.2/24 dev mfc-veth-p
for ns in mfc-ctl mfc-plant; do
  ip -n "$ns" link set lo up
done
ip -n mfc-ctl link set mfc-veth-c up
ip -n mfc-plant link set mfc-veth-p up

sed -e 's/duration = 40.0/duration = 10.0/' plants/aero/scenarios/2-complex.toml > "$WORK/scenario.toml"
"$BIN/mfc-lab" service-config --devices aero-k --scenario "$WORK/scenario.toml" > "$WORK/service.toml"
ip netns exec mfc-ctl "$BIN/controller-service" --config "$WORK/service.toml" \
  --listen udp/10.77.0.1:7447 --no-multicast-scouting >"$WORK/service.log" 2>&1 &
SVC=$!
for _ in $(seq 50); do grep -q serving "$WORK/service.log" && break; sleep 0.1; done
ip netns exec mfc-plant "$BIN/plant-agent" run --device aero-k --scenario "$WORK/scenario.toml" \
  --connect udp/10.77.0.1:7447 --no-multicast-scouting --out "$WORK/run" >"$WORK/agent.out" 2>"$WORK/agent.log" &
AGENT=$!
# Random loss both ways, in the kernel, once the session is up (zenoh does not retransmit
# handshakes or declarations lost on a UDP link). Drops are on INPUT in each namespace: a
# DROP on OUTPUT makes the sender's send() fail with EPERM, which zenoh takes for a dead
# link, whereas a real network loses packets silently.
sleep 1.5
ip netns exec mfc-plant iptables -A INPUT -i mfc-veth-p -m statistic --mode random --probability "$LOSS" -j DROP
ip netns exec mfc-ctl iptables -A INPUT -i mfc-veth-c -m statistic --mode random --probability "$LOSS" -j DROP
# The agent exits 0 when a controller answered; anything else is reported below.
wait "$AGENT" || echo "agent exit status $?"
tail -n 3 "$WORK/agent.out"
DROPS=$( (ip netns exec mfc-plant iptables -L -v -n -x; ip netns exec mfc-ctl iptables -L -v -n -x) | awk '/statistic/ {s += $1} END {print s+0}')
python3 - "$WORK/run/summary.json" "$DROPS" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
drops = int(sys.argv[2])
periods, commands = r["counters"]["periods"], r["counters"]["commands"]
pitch = r["channels"][1]
print(f"kernel suite: {drops} packets dropped by iptables; {commands}/{periods} commands applied; "
      f"pitch rms {pitch['rms']:.3e}, worst {pitch['max_abs']:.3f} rad; fallbacks {r['counters']['fallbacks']}")
ok = drops > 0 and commands > 0.5 * periods and pitch["max_abs"] < 0.1
print("kernel-suite: 1 passed, 0 failed" if ok else "kernel-suite: 0 passed, 1 failed")
sys.exit(0 if ok else 1)
PY
