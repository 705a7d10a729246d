#!/usr/bin/env bash
# The field-bus bridges across a network cut, on the project's own test hosts: a plant
# server (plants/servers/modbus_plant.py on pymodbus, then opcua_plant.py on asyncua; the DC
# motor in real time) in one network namespace, the plant agent in another, joined by a
# veth pair. iptables drops every packet of the server's connection both ways mid-run: a
# silent cut, no reset and no refusal, as a pulled cable or a dead switch gives. For each
# protocol:
#
#   1. A cut shorter than the map's reconnect_ms: the agent's requests time out, it keeps
#      trying, reconnects when the path is back, and the run completes; the outage shows as
#      overruns, and the safe value (0.25) is what the plant applies at the end.
#   2. A cut longer than reconnect_ms: the run ends (plant_failed, exit status 4) within the
#      budget plus a few timeouts, the error naming the server and the budget; the safe stop
#      is reported unconfirmed (nobody could take it: the PLC's watchdog's job).
#
# Needs root, iproute2 and iptables (installed if missing), Python 3 with venv and pip;
# skips (exit 0) when it cannot run. Usage: bash faultlab/kernel/fieldbus_cut.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
skip() { echo "fieldbus cut: skipped ($1)"; exit 0; }
[ "$(id -u)" = 0 ] || skip "needs root"
command -v ip >/dev/null || skip "no iproute2"
if ! command -v iptables >/dev/null; then
  (apt-get update -qq && apt-get install -y -qq iptables) >/dev/null 2>&1 || skip "cannot install iptables"
fi
ip netns add mfc-probe 2>/dev/null || skip "cannot create network namespaces here"
ip netns del mfc-probe

TARGET=${CARGO_TARGET_DIR:-target}
cargo build -q -p plant-agent
AGENT_BIN="$TARGET/debug/plant-agent"
PY=$(bash plants/servers/setup.sh | tail -n 1)
WORK=$(mktemp -d)
SRV_NS=mfc-mb-srv
AG_NS=mfc-mb-agent
cleanup() {
  [ -n "${SERVER:-}" ] && kill "$SERVER" 2>/dev/null || true
  ip netns del "$SRV_NS" 2>/dev/null || true
  ip netns del "$AG_NS" 2>/dev/null || true
  rm -rf "$WORK"
}
trap cleanup EXIT

ip netns add "$SRV_NS"
ip netns add "$AG_NS"
ip link add mfc-mb-s type veth peer name mfc-mb-a
ip link set mfc-mb-s netns "$SRV_NS"
ip link set mfc-mb-a netns "$AG_NS"
ip -n "$SRV_NS" addr add 10.78.0.1/24 dev mfc-mb-s
ip -n "$AG_NS" addr add 10.78.0.2/24 dev mfc-mb-a
for ns in "$SRV_NS" "$AG_NS"; do ip -n "$ns" link set lo up; done
ip -n "$SRV_NS" link set mfc-mb-s up
ip -n "$AG_NS" link set mfc-mb-a up

# One protocol: its server script, plant file, port, and how the safe value is read back.
check() { # protocol script file port address
  local proto=$1 script=$2 file=$3 port=$4 address=$5
  ip netns exec "$SRV_NS" "$PY" "plants/servers/$script" --plant dc-motor --seed 1 \
    --host 10.78.0.1 --port "$port" >"$WORK/$proto-server.out" 2>"$WORK/$proto-server.log" &
  SERVER=$!
  for _ in $(seq 200); do grep -q listening "$WORK/$proto-server.out" && break; sleep 0.1; done
  grep -q listening "$WORK/$proto-server.out" || { cat "$WORK/$proto-server.log"; echo "fieldbus cut: the $proto server never listened"; exit 1; }

  # The shipped motor file, pointed at the server's host, with the test's safe value.
  scenario() { # reconnect_ms duration
    sed -e "s#127.0.0.1:$port#10.78.0.1:$port#" -e "s#timeout_ms = 20#timeout_ms = 300#" \
        -e "s#reconnect_ms = 2000#reconnect_ms = $1#" -e "s#safe = 0.0#safe = 0.25#" \
        -e "s#duration = 20.0#duration = $2#" \
        -e "s#\"../dc-motor/controllers/ipd.toml\"#\"$PWD/plants/dc-motor/controllers/ipd.toml\"#" \
        "plants/servers/$file" >"$WORK/$proto-scenario-$1.toml"
    echo "$WORK/$proto-scenario-$1.toml"
  }
  cut() {  # both ways, silently: DROP on INPUT (a DROP on OUTPUT fails send() with EPERM)
    ip netns exec "$SRV_NS" iptables -"$1" INPUT -i mfc-mb-s -p tcp --dport "$port" -j DROP
    ip netns exec "$AG_NS" iptables -"$1" INPUT -i mfc-mb-a -p tcp --sport "$port" -j DROP
  }
  run_agent() { # scenario out
    ip netns exec "$AG_NS" "$AGENT_BIN" run --device motor-k --scenario "$1" --out "$2" \
      --listen tcp/127.0.0.1:7450 --no-multicast-scouting >"$2.out" 2>"$2.log"
  }

  # 1. A 1.5 s cut inside a 5 s budget.
  run_agent "$(scenario 5000 8.0)" "$WORK/$proto-short" & AGENT=$!
  sleep 3
  cut A; sleep 1.5; cut D
  local status=0; wait "$AGENT" || status=$?
  local safe
  if [ "$proto" = modbus ]; then
    safe=$(ip netns exec "$AG_NS" "$AGENT_BIN" probe modbus "10.78.0.1:$port" --kind input --start 2 --count 2 | awk 'NR == 2 {print $8}')
  else
    safe=$(ip netns exec "$AG_NS" "$AGENT_BIN" probe opcua "$address" --node "ns=2;s=Plant" --depth 1 | awk '/Plant.Applied/ {print $NF}')
  fi

  # 2. A cut for good inside a 1 s budget.
  run_agent "$(scenario 1000 30.0)" "$WORK/$proto-long" & AGENT=$!
  sleep 3
  cut A; local t0; t0=$(date +%s.%N)
  local status2=0; wait "$AGENT" || status2=$?
  local took; took=$(python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" "$t0" "$(date +%s.%N)")
  cut D
  kill "$SERVER" 2>/dev/null || true; wait "$SERVER" 2>/dev/null || true; SERVER=

  python3 - "$WORK" "$proto" "$address" "$status" "$safe" "$status2" "$took" <<'PY' || failed=1
import json, sys
work, proto, address = sys.argv[1], sys.argv[2], sys.argv[3]
status, safe, status2, took = int(sys.argv[4]), sys.argv[5], int(sys.argv[6]), float(sys.argv[7])
short = json.load(open(f"{work}/{proto}-short/summary.json"))
long = json.load(open(f"{work}/{proto}-long/summary.json"))
error = long["error"] or ""
checks = [
    ("short cut: the run completed (exit 3: no controller, the local law ran)",
     status == 3 and short["end"] == "completed", f"exit {status}, end {short['end']}, error {short['error']}"),
    ("short cut: the outage cost periods (overruns)", short["overruns"] > 0, f"overruns {short['overruns']}"),
    ("short cut: the plant applies the safe value at the end", safe == "0.25", f"the server says {safe!r}"),
    ("cut for good: the run ended, plant failed (exit 4)",
     status2 == 4 and long["end"] == "plant_failed", f"exit {status2}, end {long['end']}"),
    ("cut for good: the error names the server and the budget",
     address in error and "reconnect_ms = 1000" in error, error),
    ("cut for good: the safe stop is reported unconfirmed", long["safe_stop_applied"] is False, ""),
    ("cut for good: it ended within 10 s of the cut", took < 10.0, f"{took} s"),
]
failed = 0
for name, ok, detail in checks:
    print(f"fieldbus cut ({proto}): {'ok  ' if ok else 'FAIL'} {name} ({detail})")
    failed += not ok
print(f"fieldbus cut ({proto}): {len(checks) - failed} passed, {failed} failed")
sys.exit(1 if failed else 0)
PY
}

failed=0
check modbus modbus_plant.py motor-steps-modbus.toml 5020 10.78.0.1:5020
check opcua opcua_plant.py motor-steps-opcua.toml 4840 opc.tcp://10.78.0.1:4840/
exit "$failed"
