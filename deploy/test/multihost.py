#!/usr/bin/env python3
"""The multi-host deployment test: deploy/GUIDE.md, followed on separate network hosts.

Hosts are network namespaces joined by veth pairs to a bridge (in a namespace of its own),
with the guide's addresses: router 10.77.0.1, controller .2, plant-1 .11, plant-2 .12,
operator .21, and an intruder .66 that the guide does not have. Each host sees its own
/etc/mfc (`ip netns exec` bind-mounts /etc/netns/NS/mfc there); `scp` is a stand-in that
copies into it. The router is the real zenohd at the pinned version.

Phase 1 runs the guide's blocks as written (admin blocks in a scratch directory, host
blocks on their host) and checks that both plants track within MFC_TEST_MULTIHOST_RMS_RATIO
(default 1.2) of their offline twins and exit 0. A run in which a plant's own 10 ms loop
started more than MFC_TEST_MULTIHOST_MAX_OVERRUNS (10 %) of its periods late is done again
(at most 3 times, all reported, with the CPU time the hypervisor stole): the machine, not
the network, was late then; if no run kept time, that fails too.
Phase 2 starts the same commands in reverse order (plants, controller, then the router),
kills the router with SIGKILL mid-run and restarts it, changes a gain from the operator's
host (it must be in the audit trail under alice's certificate name, verified, with its old
and new value, and in the service's audit file; vera, a viewer, is refused and recorded;
alice asking as vera reaches no service), and attacks from the intruder host: forged puts, queries and subscriptions with
aero-1's certificate on aero-2's keys (counted by a witness holding the controller's
identity: 0 must arrive, against all of them on aero-1's own sample key), a client with no
certificate, plain TCP and a foreign CA (refused), and no listening socket on the plants.
Phase 3 adds a second service (host controller-2, .3) to the inventory, runs both as one
fleet under the regenerated access control, and lets a rogue on the intruder's host hold
controller-1's certificate (not the fleet's secret): its member tokens, in a made-up name
and in controller-2's, must give it no shard; its commands must all be refused by the
plant as forged. Then controller-1, which holds both plants' leases, is cut off one way
(its packets to the router dropped) for 3 s, and stopped (SIGSTOP) for 3 s and for 12 s:
each time controller-2 must take over, and the plants' own records must show no period
with commands of two holders and epochs that only go up; both plants must run to the end
served by the fleet's members only. Meanwhile the operator's identity (which may watch
commands) captures 3 s of aero-1's commands, and the rogue puts them again into two later
runs of aero-1, with the fleet up and with it down: the plant must refuse them as another
run's, apply none, and with the fleet down know it reached no controller.
Phase 4 drops the router: every process is a zenoh peer (plain TCP, port 7448), the plants
and the operator dial both members, and the members are cut from each other by bridge
port isolation, so the plants reach both (the issue's partition). A change acknowledged on
each plant first (held by both); during the partition, each member sees only itself, no
plant's lease moves and a change is not acknowledged; at the heal, the holder is killed
(SIGKILL) the moment it sees the other member join again, while they exchange the shards
the partition gave both. The survivor must hold both plants under a newer epoch, with the
changes acknowledged last (or ones sent after them), and the plants' records show no
period with two holders. The takeover times of phases 3 and 4 are printed (p50, p99, max).

Needs root, iproute2 and zenohd; without them it prints SKIP and exits 0. Exit 1 on any
failed check (all are reported). Logs and records: $MFC_MULTIHOST_LOGS (default
~/.cache/mfc-zenoh/multihost-last).

    sudo python3 deploy/test/multihost.py --bin-dir "$CARGO_TARGET_DIR/debug" [--zenohd PATH]
"""

import argparse
import csv
import datetime
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "deploy" / "GUIDE.md"
UNITS = ROOT / "deploy" / "systemd"

# Guide host -> (namespace, address). The intruder is the test's own.
HOSTS = {
    "router": ("mfc-router", "10.77.0.1"),
    "controller": ("mfc-ctl", "10.77.0.2"),
    "controller-2": ("mfc-ctl2", "10.77.0.3"),
    "plant-1": ("mfc-plant1", "10.77.0.11"),
    "plant-2": ("mfc-plant2", "10.77.0.12"),
    "operator": ("mfc-op", "10.77.0.21"),
    "intruder": ("mfc-intruder", "10.77.0.66"),
}
SWITCH = "mfc-switch"
RMS_RATIO = float(os.environ.get("MFC_TEST_MULTIHOST_RMS_RATIO", "1.2"))
# The gain change (alpha x GAIN_FACTOR on aero-2's azimuth velocity) must raise its tracking
# error over the last GAIN_WINDOW s of the run at least this many times above aero-1's, same
# window. The change lands within the first 10 s of phase 2 (6-8 s of plant time in the runs
# logged), so the window is all after it. It was the last 10 s; with the smooth dead-zone
# map aero-1 tracks twice as well and an inert controller's error is that of the
# reference's own motion, which in the last 10 s is a ramp and a hold: 1.95 times aero-1's
# there, 2.9 times over the last 20 s, in the same run.
GAIN_EFFECT = float(os.environ.get("MFC_TEST_MULTIHOST_GAIN_EFFECT", "2.0"))
GAIN_FACTOR = 1000.0
GAIN_WINDOW = 20.0
# Phase 1 is run once more when a plant's own loop started more than this fraction of its
# periods over half a period late: then the machine, not the network, was late. Runs that
# tracked well had 0.1-6 % here; the one run kept that failed the bound, 11-13 %.
MAX_OVERRUNS = float(os.environ.get("MFC_TEST_MULTIHOST_MAX_OVERRUNS", "0.10"))
ATTEMPTS = 3
FORGED = 50

failures = []
results = {}


def shard_of(device_id):
    """The device's shard, as protocol::shard_of: 64-bit FNV-1a of the id, modulo 64."""
    h = 0xcbf29ce484222325
    for b in device_id.encode():
        h = ((h ^ b) * 0x100000001b3) & 0xFFFFFFFFFFFFFFFF
    return h % 64


def sample_key(device_id):
    """Where an agent publishes its samples: the key with the device's shard in it."""
    return f"mfc/v1/shard/{shard_of(device_id)}/device/{device_id}/sample"


def log(msg):
    print(f"[multihost {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def check(ok, what, detail=""):
    log(("ok   " if ok else "FAIL ") + what + (f": {detail}" if detail else ""))
    if not ok:
        failures.append(f"{what}: {detail}")
    return ok


def sh(cmd, check_rc=True, **kw):
    r = subprocess.run(cmd, shell=isinstance(cmd, str), capture_output=True, text=True, **kw)
    if check_rc and r.returncode != 0:
        raise RuntimeError(f"{cmd}: exit {r.returncode}: {r.stderr.strip()}")
    return r


def skip(why):
    print(f"SKIP multihost deployment test: {why}", flush=True)
    sys.exit(0)


# ---------------------------------------------------------------- network

def teardown_network():
    for ns, _ in list(HOSTS.values()) + [(SWITCH, None)]:
        sh(["ip", "netns", "del", ns], check_rc=False)
        shutil.rmtree(f"/etc/netns/{ns}", ignore_errors=True)


def setup_network():
    teardown_network()
    sh(["ip", "netns", "add", SWITCH])
    sh(["ip", "-n", SWITCH, "link", "add", "br0", "type", "bridge"])
    sh(["ip", "-n", SWITCH, "link", "set", "br0", "up"])
    for i, (host, (ns, addr)) in enumerate(HOSTS.items()):
        sh(["ip", "netns", "add", ns])
        a, b = f"mfcsw{i}", f"mfcif{i}"
        sh(["ip", "link", "add", a, "type", "veth", "peer", "name", b])
        sh(["ip", "link", "set", a, "netns", SWITCH])
        sh(["ip", "link", "set", b, "netns", ns])
        sh(["ip", "-n", ns, "link", "set", b, "name", "eth0"])
        sh(["ip", "-n", ns, "addr", "add", f"{addr}/24", "dev", "eth0"])
        sh(["ip", "-n", ns, "link", "set", "eth0", "up"])
        sh(["ip", "-n", ns, "link", "set", "lo", "up"])
        sh(["ip", "-n", SWITCH, "link", "set", a, "master", "br0", "up"])
        # This host's /etc/mfc.
        Path(f"/etc/netns/{ns}/mfc").mkdir(parents=True, exist_ok=True)


SCP_SHIM = r"""#!/usr/bin/env bash
# scp stand-in for the multi-host test: SOURCE... [USER@]ADDRESS:/etc/mfc/ copies into that
# host's /etc/mfc (/etc/netns/NS/mfc, which `ip netns exec NS` mounts on /etc/mfc). Like
# scp, the directory must exist.
set -euo pipefail
args=(); for a in "$@"; do [[ $a == -* ]] || args+=("$a"); done
dst=${args[-1]}; unset 'args[-1]'
host=${dst%%:*}; host=${host#*@}; path=${dst#*:}
ns=$(awk -v h="$host" '$1 == h {print $2}' "$MFC_HOSTS_FILE")
[[ -n $ns ]] || { echo "scp stand-in: unknown host $host" >&2; exit 1; }
[[ $path == /etc/mfc/ ]] || { echo "scp stand-in: only /etc/mfc/ is mapped, not $path" >&2; exit 1; }
[[ -f /etc/netns/$ns/mfc/.made ]] || { echo "scp stand-in: $host:/etc/mfc does not exist" >&2; exit 1; }
cp -r "${args[@]}" "/etc/netns/$ns/mfc/"
"""

SSH_SHIM = r"""#!/usr/bin/env bash
# ssh stand-in for the multi-host test: [USER@]ADDRESS COMMAND... runs COMMAND on that host
# (in its namespace). `install -d ... /etc/mfc` there marks the host's /etc/mfc as made.
set -euo pipefail
host=${1#*@}; shift
ns=$(awk -v h="$host" '$1 == h {print $2}' "$MFC_HOSTS_FILE")
[[ -n $ns ]] || { echo "ssh stand-in: unknown host $host" >&2; exit 1; }
if [[ "$*" == *"install -d"*"/etc/mfc"* ]]; then touch "/etc/netns/$ns/mfc/.made"; fi
exec ip netns exec "$ns" bash -c "$*"
"""


# ---------------------------------------------------------------- guide

def guide_blocks():
    text = GUIDE.read_text()
    blocks = []
    for m in re.finditer(r"<!-- test: (\S+)([^>]*?)-->\s*```sh\n(.*?)```", text, re.S):
        host, attrs, body = m.group(1), m.group(2), m.group(3)
        a = {k: v1 or v2 for k, v1, v2 in re.findall(r'(\w+)=(?:"([^"]*)"|(\S+))', attrs)}
        if host not in HOSTS and host != "admin":
            raise RuntimeError(f"GUIDE.md names an unknown host {host!r}")
        blocks.append({"host": host, "attrs": a, "body": body})
    return blocks


class Env:
    def __init__(self, args, work, logs):
        self.work, self.logs = work, logs
        shim = work / "shim"
        shim.mkdir(parents=True, exist_ok=True)
        for name, text in [("scp", SCP_SHIM), ("ssh", SSH_SHIM)]:
            (shim / name).write_text(text)
            (shim / name).chmod(0o755)
        hosts_file = work / "hosts"
        hosts_file.write_text("".join(f"{addr} {ns}\n" for ns, addr in HOSTS.values()))
        zdir = str(Path(args.zenohd).parent)
        self.env = dict(os.environ)
        self.env["PATH"] = f"{shim}:{args.bin_dir}:{zdir}:/usr/sbin:/usr/bin:/sbin:/bin"
        self.env["MFC_HOSTS_FILE"] = str(hosts_file)
        self.env["RUST_LOG"] = "info"
        self.env["NO_COLOR"] = "1"
        self.procs = {}
        self.starts = 0
        # The operator's zenoh config: the guide's (through the router) until phase 4.
        self.op_config = "/etc/mfc/alice.json5"

    def run(self, host, script, timeout=120):
        cmd = ["bash", "-euo", "pipefail", "-c", script]
        if host != "admin":
            cmd = ["ip", "netns", "exec", HOSTS[host][0]] + cmd
        return subprocess.run(cmd, cwd=self.work, env=self.env, capture_output=True, text=True,
                              timeout=timeout)

    def start(self, host, name, command):
        self.starts += 1
        out = open(self.logs / f"{name}.{self.starts}.log", "w")
        cmd = ["ip", "netns", "exec", HOSTS[host][0], "bash", "-c", "exec " + command]
        p = subprocess.Popen(cmd, cwd=self.work, env=self.env, stdout=out, stderr=subprocess.STDOUT,
                             start_new_session=True)
        self.procs[name] = (p, out, host, command, out.name)
        log(f"started {name} on {host} (pid {p.pid}): {command}")
        return p

    def stop(self, name, sig=signal.SIGTERM, timeout=20):
        p = self.procs[name][0]
        if p.poll() is None:
            p.send_signal(sig)
            try:
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        return p.returncode

    def wait(self, name, timeout):
        p = self.procs[name][0]
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def log_text(self, name):
        return Path(self.procs[name][4]).read_text(errors="replace")

    def kill_all(self):
        for name, (p, out, *_rest) in self.procs.items():
            if p.poll() is None:
                p.terminate()
        deadline = time.time() + 15
        for name, (p, out, *_rest) in self.procs.items():
            try:
                p.wait(max(0.1, deadline - time.time()))
            except subprocess.TimeoutExpired:
                p.kill()
            out.close()


# ---------------------------------------------------------------- helpers

def mfcctl(env, *args):
    r = env.run("operator", f"mfcctl --zenoh-config {env.op_config} --key-file /etc/mfc/alice.auth --json " +
                " ".join(args), timeout=30)
    if r.returncode != 0:
        return None, r.stderr.strip()
    try:
        return json.loads(r.stdout), None
    except json.JSONDecodeError as e:
        return None, f"{e}: {r.stdout[:200]}"


def audit_of(env, who, device):
    """`mfcctl audit DEVICE --json` as `who` (its own bundle): the device's entries."""
    r = env.run("operator", f"mfcctl --zenoh-config /etc/mfc/{who}.json5 --key-file /etc/mfc/{who}.auth "
                f"--json audit {device}", timeout=30)
    if r.returncode != 0:
        return None, r.stderr.strip()
    logs = json.loads(r.stdout)
    return (logs[0]["entries"] if logs else []), None


def audit_checks(env, alpha, results):
    """Phase 2: alice's change is on the record under her certificate's name; vera's (a
    viewer) is refused and recorded; alice asking as vera reaches no service."""
    entries, err = audit_of(env, "vera", "aero-2")
    if not check(entries is not None, "the viewer reads aero-2's audit trail", err or ""):
        return
    mine = [e for e in entries if e.get("operator") == "alice" and e.get("accepted")]
    moved = [c for e in mine for c in e.get("changes", []) if c["what"] == "channel 0 alpha"]
    check(any(abs(float(c["new"]) - alpha) <= 1e-9 * abs(alpha) for c in moved),
          "alice's alpha change is in the audit trail with its new value", json.dumps(mine)[-400:])
    check(all(e.get("verified") and e.get("role") == "operator" and e.get("member") == "controller-1"
              for e in mine) and mine,
          "alice's entries are verified (her certificate's name), role operator, decided by controller-1",
          json.dumps(mine)[-400:])
    set_alpha = "set aero-2 --channel 0 alpha=1"
    r = env.run("operator", f"mfcctl --zenoh-config /etc/mfc/vera.json5 --key-file /etc/mfc/vera.auth {set_alpha}",
                timeout=30)
    check(r.returncode != 0 and "is a viewer" in r.stderr,
          "vera (a viewer) cannot change a gain, and is told why", f"exit {r.returncode}: {r.stderr.strip()[-200:]}")
    r = env.run("operator", f"mfcctl --zenoh-config /etc/mfc/alice.json5 --key-file /etc/mfc/alice.auth "
                f"--operator vera --timeout-ms 1500 {set_alpha}", timeout=30)
    check(r.returncode != 0 and "no answer" in r.stderr,
          "alice cannot ask as vera: the router drops the request", f"exit {r.returncode}: {r.stderr.strip()[-200:]}")
    after, err = audit_of(env, "alice", "aero-2")
    if not check(after is not None, "alice reads aero-2's audit trail", err or ""):
        return
    veras = [e for e in after if e.get("operator") == "vera"]
    check(len(veras) == 1 and not veras[0]["accepted"] and "viewer" in veras[0]["reason"],
          "vera's attempt is recorded once, refused, with why; alice's attempt as vera is not there",
          json.dumps([(e["operator"], e["accepted"], e["reason"]) for e in after]))
    check(len(after) == len(entries) + 1, "exactly one more entry (vera's)",
          f"{len(entries)} then {len(after)}")
    results["audit_aero2"] = after
    # The same decisions are in the service's audit file, fsynced before each reply.
    path = Path("/var/lib/mfc/audit/controller-1.jsonl")
    lines = [json.loads(l) for l in path.read_text().splitlines()] if path.exists() else []
    on_file = [(l["operator"], l["accepted"], l["n"]) for l in lines if l["device"] == "aero-2"]
    served = [(e["operator"], e["accepted"], e["n"]) for e in after]
    check(on_file == served, "the audit file holds aero-2's entries, as the service answers them",
          f"file {on_file[-3:]} vs reply {served[-3:]}")


# The shared console of the guide (`desk`, on the operator's host).
DESK = "https://10.77.0.21:8443"


def desk(env, path, cert=None, body=None):
    """curl on the operator's host to the shared console, checking its certificate with
    the fleet's CA: (HTTP status, JSON body or None); status 0 if no HTTP answer."""
    cmd = "curl -sS -o - -w '\\n%{http_code}' --cacert /etc/mfc/ca.pem "
    if cert:
        cmd += f"--cert /etc/mfc/{cert}.pem --key /etc/mfc/{cert}.key "
    if body is not None:
        cmd += f"-H 'Content-Type: application/json' --data '{json.dumps(body)}' "
    r = env.run("operator", cmd + DESK + path, timeout=30)
    text, _, code = r.stdout.rpartition("\n")
    try:
        return int(code), (json.loads(text) if text.strip() else None)
    except ValueError:
        return 0, r.stderr.strip()[-200:]


def console_checks(env, alpha, results):
    """Phase 2: the shared console acts for the person its HTTPS client certificate names
    (alice's change is audited under her name), refuses nobody and viewers, and its own
    certificate may ask as its people only."""
    st, body = desk(env, "/api/devices")
    check(st == 401, "the shared console refuses its API to nobody (401)", f"{st} {body}")
    st, me = desk(env, "/api/me", cert="alice")
    check(st == 200 and me and (me.get("name"), me.get("role"), me.get("proof")) == ("alice", "operator", "certificate"),
          "alice's certificate logs her in to the shared console", f"{st} {me}")
    new = alpha * 1.001
    change = {"channel": 0, "fields": {"alpha": new}}
    st, body = desk(env, "/api/devices/aero-2/gains", cert="vera", body=change)
    check(st == 403 and "viewer" in str(body), "vera (a viewer) cannot change through the console (403)",
          f"{st} {body}")
    st, body = desk(env, "/api/devices/aero-2/gains", cert="alice", body=change)
    check(st == 200 and body and body.get("accepted"), "alice changes aero-2's alpha through the console",
          f"{st} {body}")
    entries, err = audit_of(env, "vera", "aero-2")
    last = entries[-1] if entries else {}
    moved = [c for c in last.get("changes", []) if c["what"] == "channel 0 alpha"]
    check(last.get("operator") == "alice" and last.get("verified") and last.get("accepted")
          and moved and abs(float(moved[0]["new"]) - new) <= 1e-9 * abs(new),
          "the console's change is audited under alice's name (verified), not the console's",
          json.dumps(last)[-400:] if last else str(err))
    results["console_change"] = last
    as_who = lambda who: env.run("operator", f"mfcctl --zenoh-config /etc/mfc/desk.json5 --key-file "
                                 f"/etc/mfc/desk.auth --operator {who} --timeout-ms 1500 config aero-2", timeout=30)
    r = as_who("alice")
    check(r.returncode == 0, "the console's certificate may ask as alice (one of its people)",
          r.stderr.strip()[-200:])
    r = as_who("mallory")
    check(r.returncode != 0 and "no answer" in r.stderr,
          "the console's certificate cannot ask as anyone else: the router drops it",
          f"exit {r.returncode}: {r.stderr.strip()[-200:]}")


def devices_up(env):
    d, err = mfcctl(env, "devices")
    if d is None:
        return set(), err
    served = {dev["device_id"] for svc in d.get("services", []) for dev in svc.get("devices", [])}
    return served & set(d.get("plants_up", [])), None


def wait_devices(env, want, timeout):
    deadline = time.time() + timeout
    last = None
    while time.time() < deadline:
        up, err = devices_up(env)
        last = (up, err)
        if want <= up:
            return True, last
        time.sleep(1)
    return False, last


def probe(env, host, config, *args, timeout=60):
    cmd = "zenoh-probe " + (f"--zenoh-config {config} " if config else "") + " ".join(args)
    r = env.run(host, cmd, timeout=timeout)
    line = (r.stdout.strip().splitlines() or ["{}"])[-1]
    try:
        return r.returncode, json.loads(line)
    except json.JSONDecodeError:
        return r.returncode, {"raw": r.stdout + r.stderr}


def read_run(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return rows


def rms_err(rows, ch, t0, t1):
    e = [float(r[f"{ch}_ref"]) - float(r[ch]) for r in rows
         if r[ch] and r[f"{ch}_ref"] and t0 <= float(r["t"]) <= t1]
    return math.sqrt(sum(x * x for x in e) / len(e)) if e else float("nan")


def steal_since(start):
    """The CPU time stolen by the hypervisor since `start` (a fraction of all CPU time),
    or, with None, a new start: on a shared VM, what the machine took from the loops."""
    f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    total, steal = sum(f[:8]), f[7] if len(f) > 7 else 0
    if start is None:
        return (total, steal)
    return (steal - start[1]) / max(1, total - start[0])


def cert_hashes(fleet):
    """File name -> content of every certificate and key in the fleet's bundles (not the CA)."""
    out = {}
    for f in fleet.glob("*/*/*"):
        if f.suffix in (".pem", ".key") and f.name != "ca.pem":
            out[f.name] = f.read_bytes()
    for f in (fleet / "router").glob("*"):
        if f.suffix in (".pem", ".key") and f.name != "ca.pem":
            out[f.name] = f.read_bytes()
    return out


def client_config(path):
    """A generated json5 config (JSON under // comment lines) as a dict."""
    return json.loads("\n".join(l for l in Path(path).read_text().splitlines()
                                if not l.lstrip().startswith("//")))


# ---------------------------------------------------------------- the test

def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin-dir", required=True, help="directory with the workspace's binaries")
    ap.add_argument("--zenohd", default=shutil.which("zenohd") or
                    str(Path.home() / ".cache/mfc-zenoh/tools/bin/zenohd"))
    ap.add_argument("--require", action="store_true",
                    help="fail instead of skipping when the test cannot run (CI sets it)")
    args = ap.parse_args()
    global skip
    if args.require:
        def skip(why):  # noqa: F811 -- CI must not go green without the test
            sys.exit(f"multihost: cannot run, and --require was given: {why}")

    if os.geteuid() != 0:
        skip("needs root (network namespaces)")
    if not shutil.which("ip"):
        skip("needs iproute2 (`ip`)")
    if not Path(args.zenohd).is_file():
        skip(f"no zenohd at {args.zenohd} (.ci/run installs it: cargo install zenohd --version 1.10.2)")
    v = sh([args.zenohd, "--version"], check_rc=False).stdout
    if "1.10.2" not in v:
        skip(f"{args.zenohd} is not zenohd 1.10.2, the pinned version: {v.strip()[:80]}")
    for b in ["controller-service", "plant-agent", "mfcctl", "mfc-deploy", "mfc-lab", "zenoh-probe", "mfc-console"]:
        if not (Path(args.bin_dir) / b).is_file():
            sys.exit(f"multihost: {b} is not in {args.bin_dir}: cargo build --workspace --bins")
    r = sh(["ip", "netns", "add", "mfc-probe-ns"], check_rc=False)
    if r.returncode != 0:
        skip(f"cannot make network namespaces: {r.stderr.strip()}")
    sh(["ip", "netns", "del", "mfc-probe-ns"], check_rc=False)

    logs = Path(os.environ.get("MFC_MULTIHOST_LOGS", Path.home() / ".cache/mfc-zenoh/multihost-last"))
    shutil.rmtree(logs, ignore_errors=True)
    logs.mkdir(parents=True)
    work = logs / "admin"
    work.mkdir()
    made_etc = not Path("/etc/mfc").exists()
    Path("/etc/mfc").mkdir(exist_ok=True)
    # The audit trail too: the service gives each device its entries back from the file,
    # and the checks count this run's.
    for d in ["aero-1", "aero-2", "audit"]:
        shutil.rmtree(f"/var/lib/mfc/{d}", ignore_errors=True)
    env = None
    t_start = time.time()
    try:
        setup_network()
        env = Env(args, work, logs)
        run_test(env, args)
    except Exception as e:  # a setup step failed: report it as a failure, clean up below
        check(False, "the test ran to its end", repr(e))
    finally:
        if env:
            env.kill_all()
        teardown_network()
        for d in ["aero-1", "aero-2"]:
            if Path(f"/var/lib/mfc/{d}").exists():
                shutil.move(f"/var/lib/mfc/{d}", logs / f"var-lib-{d}-last")
        if made_etc:
            shutil.rmtree("/etc/mfc", ignore_errors=True)
    results["seconds"] = round(time.time() - t_start, 1)
    (logs / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    log(f"results: {logs / 'results.json'}; logs in {logs}")
    if failures:
        print("\nmultihost: FAILED checks:\n  " + "\n  ".join(failures), flush=True)
        sys.exit(1)
    log(f"all checks passed in {results['seconds']} s")


def run_test(env, args):
    blocks = guide_blocks()
    bg = {}
    # ---------------- units: their ExecStart lines are the guide's commands
    units = {}
    for f in UNITS.glob("*.service"):
        m = re.search(r"^ExecStart=(.*)$", f.read_text(), re.M)
        units[f.name] = m.group(1).replace("/usr/local/bin/", "") if m else None
    for b in blocks:
        if "bg" in b["attrs"]:
            bg[b["attrs"]["bg"]] = (b["host"], b["body"].strip())
    expect = {"mfc-router.service": ("router", None), "mfc-controller@.service": ("controller", "controller-1"),
              "mfc-agent@.service": ("aero-1", "aero-1"), "mfc-gateway@.service": ("cell-1", "cell-1")}
    for unit, (name, inst) in expect.items():
        line = units.get(unit)
        line = line.replace("%i", inst) if line and inst else line
        check(line == bg.get(name, (None, None))[1], f"{unit} runs the guide's command",
              f"{line!r} vs {bg.get(name, (None, None))[1]!r}")

    # The offline twin (same scenario, same duration), before anything runs.
    r = env.run("admin", "mfc-lab sim --scenario 2 --out offline")
    check(r.returncode == 0, "offline twin runs", r.stderr[-300:])
    offline = json.loads((env.work / "offline" / "summary.json").read_text())
    off = {c["name"]: c["rms"] for c in offline["channels"]}
    results["offline_rms"] = off

    # ---------------- phase 1: the guide as written
    log("phase 1: the guide's blocks, in order")
    steal0 = steal_since(None)
    for b in blocks:
        host, a, body = b["host"], b["attrs"], b["body"]
        if "skip" in a:
            log(f"skipped a {host} block: {a['skip']}")
            continue
        if a.get("phase") == "day2":
            continue
        if "bg" in a:
            env.start(host, a["bg"], body.strip())
            continue
        tries = int(a.get("retry", "1"))
        for i in range(tries):
            r = env.run(host, body)
            if r.returncode == 0:
                break
            time.sleep(1)
        (env.logs / f"block-{host}-{blocks.index(b)}.log").write_text(r.stdout + r.stderr)
        if not check(r.returncode == 0, f"guide block on {host} runs",
                     f"exit {r.returncode}: {r.stderr.strip()[-400:]}"):
            raise RuntimeError("the guide's setup failed; later checks would only repeat it")
    ok, last = wait_devices(env, {"aero-1", "aero-2"}, 30)
    check(ok, "the operator, through the router, lists both plants up", str(last))
    status, err = mfcctl(env, "status", "aero-1")
    check(status is not None, "the operator reads aero-1's status", err or "")
    services, err = mfcctl(env, "services")
    check(services is not None and all(x.get("authenticated") for x in services),
          "the service checks proofs of origin (it has the fleet's secret)", str(services or err))


    # A run whose own 10 ms loop was starved (the agents count periods started more than
    # half a period late) measures the machine, not the deployment: such a run is done
    # once more, and both are reported. The rerun is judged whatever its overruns.
    for attempt in range(1, ATTEMPTS + 1):
        codes, summaries = {}, {}
        for d in ["aero-1", "aero-2"]:
            codes[d] = env.wait(d, 120)
            summaries[d] = json.loads(Path(f"/var/lib/mfc/{d}/summary.json").read_text())
        over = {d: s["overruns"] / max(1, s["counters"]["periods"]) for d, s in summaries.items()}
        results[f"phase1_attempt{attempt}_overrun_fraction"] = over
        results[f"phase1_attempt{attempt}_cpu_steal"] = steal_since(steal0)
        for d in ["aero-1", "aero-2"]:
            results[f"phase1_attempt{attempt}_{d}_rms_ratio"] = {
                c["name"]: c["rms"] / off[c["name"]] for c in summaries[d]["channels"]}
            shutil.move(f"/var/lib/mfc/{d}", env.logs / f"phase1-{d}-attempt{attempt}")
        if max(over.values()) <= MAX_OVERRUNS:
            break
        log(f"phase 1: the plants' own loops overran ({over}; CPU steal "
            f"{results[f'phase1_attempt{attempt}_cpu_steal']:.0%}): the machine was late")
        if attempt < ATTEMPTS:
            steal0 = steal_since(None)
            for d in ["aero-1", "aero-2"]:
                env.start(bg[d][0], d, bg[d][1])
    results["phase1_attempts"] = attempt
    check(max(over.values()) <= MAX_OVERRUNS,
          f"phase 1 ran once with the plants' loops on time (overruns at most {MAX_OVERRUNS:.0%})",
          f"attempt {attempt} of at most {ATTEMPTS}, overruns {over}" +
          ("" if max(over.values()) <= MAX_OVERRUNS else ": this machine cannot judge tracking now"))
    for d in ["aero-1", "aero-2"]:
        auth = summaries[d].get("auth", {})
        check(auth.get("authenticated") is True and auth.get("forged") == 0,
              f"phase 1: {d}'s samples were sealed and every command it got proved its origin",
              str(auth))
        check(codes[d] == 0, f"phase 1: {d} exits 0 (a controller answered)", f"exit {codes[d]}")
        for ch, q in results[f"phase1_attempt{attempt}_{d}_rms_ratio"].items():
            check(q <= RMS_RATIO, f"phase 1: {d} {ch} tracks within {RMS_RATIO}x of offline",
                  f"ratio {q:.3f} (attempt {attempt}, loop overruns {over[d]:.1%})")
    gateway_plants(env, off)

    # ---------------- phase 2: reverse start order, router restart, gain change, attacks
    log("phase 2: plants first, then the controller, then the router")
    env.stop("controller")
    env.stop("router")
    for d in ["aero-1", "aero-2"]:
        env.start(bg[d][0], d, bg[d][1])
    time.sleep(1)
    env.start(bg["controller"][0], "controller", bg["controller"][1])
    time.sleep(6.5)
    for d in ["aero-1", "aero-2"]:
        alive = env.procs[d][0].poll() is None
        check(alive, f"{d} waits for a router that is not there yet (start order)")
        check("not connected after" in env.log_text(d), f"{d} says it is not connected yet")
    env.start(bg["router"][0], "router", bg["router"][1])
    ok, last = wait_devices(env, {"aero-1", "aero-2"}, 30)
    check(ok, "phase 2: both plants served once the router is up", str(last))
    # Plants listen on nothing, while they run: no way around the router.
    plants_running(env, "when their sockets are listed")
    plant_udp = {}
    for host in ["plant-1", "plant-2"]:
        r = env.run(host, "ss -Htuanp")
        lines = [l for l in r.stdout.splitlines() if l.strip()]
        results[f"{host}_sockets"] = lines
        check(any("plant-agent" in l for l in lines),
              f"control: {host}'s agent has its socket towards the router", "; ".join(lines))
        check(not any(l.startswith("tcp") and "LISTEN" in l for l in lines),
              f"no TCP socket listens on {host}", "; ".join(lines))
        # QUIC's client socket is UDP and unconnected: it must refuse a connection anyway
        # (checked from the intruder's host below).
        plant_udp[host] = [l.split()[4].rsplit(":", 1)[1] for l in lines
                           if l.startswith("udp") and "plant-agent" in l]
    env.plant_udp = plant_udp
    time.sleep(2)

    log("router: SIGKILL, back after 2 s")
    env.stop("router", sig=signal.SIGKILL)
    time.sleep(2)
    env.start(bg["router"][0], "router", bg["router"][1])
    t_back = time.time()
    ok, last = wait_devices(env, {"aero-1", "aero-2"}, 30)
    results["router_restart_operator_sees_plants_after_s"] = round(time.time() - t_back, 2)
    check(ok, "after the router's restart, both plants are served again", str(last))
    time.sleep(2)

    # A gain change from the operator's host: aero-2's azimuth-velocity alpha x GAIN_FACTOR.
    cfg, err = mfcctl(env, "config", "aero-2")
    alpha = None
    if check(cfg is not None, "the operator reads aero-2's configuration", err or ""):
        alpha = find_alpha(cfg, 0)
    if check(alpha is not None, "aero-2 channel 0 has an alpha", json.dumps(cfg)[:300]):
        new = alpha * GAIN_FACTOR
        r = env.run("operator", f"mfcctl --zenoh-config /etc/mfc/alice.json5 --key-file /etc/mfc/alice.auth set aero-2 --channel 0 alpha={new}")
        check(r.returncode == 0, "the operator changes aero-2's alpha", r.stderr.strip()[-300:])
        cfg2, err = mfcctl(env, "config", "aero-2")
        got = find_alpha(cfg2, 0) if cfg2 else None
        check(got is not None and abs(got - new) <= 1e-9 * abs(new),
              "the service's configuration shows the new alpha", f"{got} vs {new}")
        results["alpha_change"] = {"from": alpha, "to": new}
        audit_checks(env, new, results)
        console_checks(env, new, results)

    attacks(env)

    for d in ["aero-1", "aero-2"]:
        rc = env.wait(d, 120)
        check(rc == 0, f"phase 2: {d} exits 0 (served at the end)", f"exit {rc}")
    runs = {d: read_run(f"/var/lib/mfc/{d}/run.csv") for d in ["aero-1", "aero-2"]}
    for d, rows in runs.items():
        modes = [r["mode"] for r in rows]
        first = modes.index("remote") if "remote" in modes else None
        last_r = len(modes) - 1 - modes[::-1].index("remote") if "remote" in modes else None
        # The outage: the longest stretch on the local fallback between remote periods.
        # `holding` (a late command: the last remote one is held) is still remote control.
        stretches, start = [], None
        for i in range(first or 0, (last_r or 0) + 1):
            if modes[i] in ("local", "safe_stop") and start is None:
                start = i
            elif modes[i] not in ("local", "safe_stop") and start is not None:
                stretches.append((start, i))
                start = None
        outage = max(stretches, key=lambda s: s[1] - s[0], default=None)
        n_out = outage[1] - outage[0] if outage else 0
        results[f"phase2_{d}_fallback_periods"] = n_out
        check(n_out > 0, f"{d} fell back to its local controller while the router was down",
              f"{n_out} periods local")
        after = modes[outage[1]:] if outage else []
        served = sum(1 for m in after if m in ("remote", "holding"))
        results[f"phase2_{d}_after_outage"] = {
            "periods": len(after), "remote": after.count("remote"), "holding": after.count("holding")}
        check(len(after) >= 500 and served >= 0.98 * len(after),
              f"{d} came back under remote control and stayed",
              f"{served}/{len(after)} periods served after the outage "
              f"({after.count('remote')} remote, {after.count('holding')} holding a late command)")
    t_end = min(float(rows[-1]["t"]) for rows in runs.values())
    ch = "azimuth_velocity"
    e1 = rms_err(runs["aero-1"], ch, t_end - GAIN_WINDOW, t_end)
    e2 = rms_err(runs["aero-2"], ch, t_end - GAIN_WINDOW, t_end)
    results["gain_change_error_ratio_aero2_over_aero1"] = e2 / e1
    check(e2 >= GAIN_EFFECT * e1, f"the gain change shows in aero-2's tracking ({ch})",
          f"RMS error over the last {GAIN_WINDOW:.0f} s: aero-2 {e2:.3e}, aero-1 {e1:.3e}, "
          f"ratio {e2 / e1:.2f}")
    for d in ["aero-1", "aero-2"]:
        shutil.move(f"/var/lib/mfc/{d}", env.logs / f"phase2-{d}")

    router_outages(env, bg, results)

    # ---------------- day two: adding a device and rotating one touch nothing else
    for b in blocks:
        if b["attrs"].get("phase") != "day2" or "skip" in b["attrs"]:
            continue
        before = cert_hashes(env.work / "fleet")
        r = env.run("admin", b["body"])
        check(r.returncode == 0, "day-two guide block runs", r.stderr.strip()[-300:])
        after = cert_hashes(env.work / "fleet")
        new = {n for n in after if n not in before}
        changed = {n for n in before if after.get(n) != before[n]}
        want_new = {f"{x}.{e}" for x in b["attrs"]["issues"].split() for e in ("pem", "key")}
        want_changed = {f"{x}.{e}" for x in b["attrs"]["reissues"].split() for e in ("pem", "key")}
        check(new == want_new and changed == want_changed,
              f"generate issued {sorted(want_new) or 'nothing new'} and reissued {sorted(want_changed) or 'nothing'}",
              f"new {sorted(new)}, changed {sorted(changed)}")
    acl = (env.work / "fleet" / "router" / "zenohd.json5").read_text()
    check("mfc/v1/device/aero-3/sample" in acl, "the router's access control names the new device")

    if fleet_phase(env, bg, results):
        peer_phase(env, results)
    takeover_figures(results)


# Router outages (s): short, longer than the clients' lease (3 s), and long.
OUTAGES = [2.0, 6.0, 15.0]

# The operator's query during a fault: the timeout it gives, and how much longer the whole
# command (a process started, a session opened, the query, the exit) may take on a busy
# machine: the product's promise is the timeout; the margin is the machine.
QUERY_TIMEOUT_MS = 1500
QUERY_MARGIN_S = float(os.environ.get("MFC_TEST_MULTIHOST_QUERY_MARGIN_S", "1.0"))


def timed_status(env, device):
    """`mfcctl --timeout-ms QUERY_TIMEOUT_MS --json status DEVICE` from the operator's host:
    (seconds it took, exit code, the status or the error)."""
    t0 = time.time()
    r = env.run("operator", f"mfcctl --zenoh-config {env.op_config} --key-file /etc/mfc/alice.auth "
                f"--timeout-ms {QUERY_TIMEOUT_MS} --json status {device}", timeout=60)
    took = time.time() - t0
    if r.returncode != 0:
        return took, r.returncode, r.stderr.strip()[-300:]
    try:
        return took, 0, json.loads(r.stdout)
    except json.JSONDecodeError:
        return took, 0, r.stdout[:300]


def log_time(line):
    """The wall-clock time a log line of ours starts with (tracing's RFC 3339, UTC)."""
    try:
        return datetime.datetime.fromisoformat(line.split()[0]).timestamp()
    except (ValueError, IndexError):
        return None


def resumed_after(env, name, offset, since):
    """Seconds from `since` (wall clock) to the first 'remote control resumes' line that
    `name`'s log has after `offset` bytes, or None."""
    with open(env.procs[name][4], errors="replace") as f:
        f.seek(offset)
        for line in f:
            if "remote control resumes" in line:
                t = log_time(line)
                if t is not None and t >= since:
                    return round(t - since, 3)
    return None


def router_outages(env, bg, results):
    """The router killed for each of OUTAGES while both plants run: the time from its
    return to each plant's first remote command again, and an operator's query during the
    outage (it must end within its timeout, with an error that says what it waited for)."""
    log(f"router outages of {', '.join(f'{s:.0f}' for s in OUTAGES)} s")
    for d in ["aero-1", "aero-2"]:
        env.start(bg[d][0], d, f"{bg[d][1]} --duration {10 + sum(OUTAGES) + 15 * len(OUTAGES):.0f}")
    for secs in OUTAGES:
        ok, last = wait_devices(env, {"aero-1", "aero-2"}, 30)
        check(ok, f"both plants served before the {secs:.0f} s router outage", str(last))
        time.sleep(2)
        offsets = {d: Path(env.procs[d][4]).stat().st_size for d in ["aero-1", "aero-2"]}
        env.stop("router", sig=signal.SIGKILL)
        t_kill = time.time()
        took, rc, said = timed_status(env, "aero-1")
        results[f"router_outage_{secs:.0f}s_query"] = {"took_s": round(took, 3), "exit": rc, "said": said}
        check(rc != 0 and took <= QUERY_TIMEOUT_MS / 1000 + QUERY_MARGIN_S,
              f"router down {secs:.0f} s: the operator's query ends within its timeout, with an error",
              f"{took:.2f} s (timeout {QUERY_TIMEOUT_MS} ms), exit {rc}: {said}")
        time.sleep(max(0.0, t_kill + secs - time.time()))
        env.start(bg["router"][0], "router", bg["router"][1])
        t_back = time.time()
        deadline = t_back + 20
        got = {}
        while time.time() < deadline and len(got) < 2:
            time.sleep(0.2)
            for d in ["aero-1", "aero-2"]:
                if d not in got:
                    r = resumed_after(env, d, offsets[d], t_back)
                    if r is not None:
                        got[d] = r
        for d in ["aero-1", "aero-2"]:
            results[f"router_outage_{secs:.0f}s_{d}_remote_after_return_s"] = got.get(d)
            check(d in got, f"router down {secs:.0f} s: {d} is under remote control again",
                  f"{got.get(d)} s after the router's return")
        log(f"router back after {secs:.0f} s: remote control {got} s after its return")
    for d in ["aero-1", "aero-2"]:
        env.stop(d)


# SIGSTOP of the member holding the plants' leases: (seconds stopped, the pause's start and
# end on this clock). 0.5 s is shorter than zenoh's link lease (1 s in the generated
# configs: the fleet still sees the member); 4 s and 12 s longer (the fleet sees it leave,
# and come back).
PAUSES = [0.5, 4.0, 12.0]


# A one-way partition first: controller-1's host drops what it sends to the router for this
# long, while it still receives the plants' samples (it sees the lease move and keeps quiet).
ONE_WAY = 3.0

# The plants' run in phase 3 (s): the faults and the waits between them fit in it.
FLEET_RUN = 60


def holder_back(env, after):
    """Each fault is judged on a plant controller-1 holds: after one, wait until it holds
    both plants again (the member a plant's shard belongs to takes it back at the end of
    its stand-in's term, some seconds after it is healthy again), however long that takes
    on a busy machine, rather than for a fixed gap that the return may overrun."""
    ok, last = wait_leases(env, ("aero-1", "aero-2"), lambda lease: lease[0] == "controller-1", 30)
    check(ok, f"phase 3: controller-1 holds both plants again after {after}", str(last))


def pause_the_holder(env):
    """Cut controller-1 (it holds both plants' leases) off one way for ONE_WAY s, then stop
    it for each of PAUSES, each fault once it holds both plants again; returns the faults,
    for the report."""
    done = []
    rule = ["OUTPUT", "-d", HOSTS["router"][1], "-j", "DROP"]
    ns = ["ip", "netns", "exec", HOSTS["controller"][0], "iptables"]
    holder_back(env, "the start")
    plants_running(env, "before the one-way partition of the holder")
    log(f"controller-1 cut off one way (its packets to the router dropped) for {ONE_WAY:.0f} s")
    sh(ns + ["-A"] + rule)
    time.sleep(ONE_WAY)
    sh(ns + ["-D"] + rule)
    done.append("one-way")
    pid = env.procs["controller"][0].pid
    for secs in PAUSES:
        holder_back(env, done[-1])
        plants_running(env, f"before a {secs:g} s pause of the holder")
        log(f"SIGSTOP controller-1 for {secs:g} s")
        os.kill(pid, signal.SIGSTOP)
        t_stop = time.time()
        # The operator asks while the holder is stopped: the answer (the member that took
        # over, with fresh word of the plant) or an error, within the timeout.
        time.sleep(min(1.0, secs / 3))
        took, rc, said = timed_status(env, "aero-1")
        key = f"pause_{secs:g}s_query"
        results[key] = {"took_s": round(took, 3), "exit": rc, "said": said}
        check(took <= QUERY_TIMEOUT_MS / 1000 + QUERY_MARGIN_S,
              f"the operator's query during a {secs:g} s pause of the holder ends within its timeout",
              f"{took:.2f} s (timeout {QUERY_TIMEOUT_MS} ms), exit {rc}")
        time.sleep(max(0.0, t_stop + secs - time.time()))
        os.kill(pid, signal.SIGCONT)
        # Just after the resume: whoever answers, the word on the lease is the freshest.
        took, rc, said = timed_status(env, "aero-1")
        results[f"pause_{secs:g}s_query_after_resume"] = {"took_s": round(took, 3), "exit": rc, "said": said}
        if rc == 0 and isinstance(said, dict):
            check(said.get("heard_ms_ago", 0) <= 1000,
                  f"just after a {secs:g} s pause, the status is the freshest word of the plant",
                  f"answered by {said.get('answered_by')}, heard {said.get('heard_ms_ago')} ms ago, "
                  f"lease {said.get('lease_holder')} epoch {said.get('lease_epoch')}")
        done.append(f"SIGSTOP {secs:g} s")
    time.sleep(4)
    return done


def one_holder_at_a_time(phase, d, spans):
    """The plant's own record of who commanded it (its lease spans, in its 10 ms periods):
    no period with commands of two holders, epochs only up."""
    overlap = [(a, b) for a, b in zip(spans, spans[1:]) if b["first"] <= a["last"]]
    check(not overlap, f"{phase}: {d} never applied commands of two holders in one period",
          str(overlap)[:300])
    epochs = [sp["epoch"] for sp in spans]
    check(epochs == sorted(set(epochs)), f"{phase}: {d}'s lease epochs only went up", str(epochs))


def judge_takeovers(d, spans, pauses, results):
    """From the plant's own record of who commanded (its lease spans): never two holders
    at once, epochs only up, and each pause of the holder ended by another member taking
    over. The takeover time is counted in the plant's periods (10 ms), from the last period
    the paused holder commanded to the first its successor did."""
    one_holder_at_a_time("phase 3", d, spans)
    results[f"phase3_{d}_spans"] = [(sp["holder"], sp["epoch"], sp["first"], sp["last"])
                                    for sp in spans]
    # Whoever answered first may hold a plant for its first second or two, then hand it
    # to its preferred member: the faults come later, so the spans before controller-1's
    # first are the start, not a takeover.
    first = next((i for i, sp in enumerate(spans) if sp["holder"] == "controller-1"), None)
    if first is None:
        log(f"phase 3: {d} was never held by controller-1: its pauses judge nothing here")
        return False
    spans = spans[first:]
    takeovers = [b["first"] - a["last"] for a, b in zip(spans, spans[1:])
                 if a["holder"] == "controller-1" and b["holder"] == "controller-2"]
    results[f"phase3_{d}_takeover_periods"] = takeovers
    check(len(takeovers) >= len(pauses),
          f"phase 3: {d}: controller-2 took over at each fault of controller-1 ({', '.join(pauses)})",
          f"takeovers after {takeovers} periods; spans {results[f'phase3_{d}_spans']}")
    return True


def fleet_view(env, want, timeout):
    """The services' statuses once `want` members each see both and own disjoint shards
    covering all 64, the same in two reads 1.5 s apart (an owner outranked by a newcomer
    keeps a shard up to its release timeout, 1 s, so one read may catch a handover); or
    the last seen after `timeout` s."""
    deadline, last, seen = time.time() + timeout, None, None
    while time.time() < deadline:
        last, _ = mfcctl(env, "services")
        owned = None
        if last and {x["controller_id"] for x in last} == want and all(
                set(x.get("fleet_members", [])) == want for x in last):
            sets = [set(x.get("owned_shards", [])) for x in last]
            if sum(len(o) for o in sets) == 64 and len(set().union(*sets)) == 64:
                owned = {x["controller_id"]: sorted(x.get("owned_shards", [])) for x in last}
        if owned is not None and owned == seen:
            return last, True
        seen = owned
        time.sleep(1.5)
    return last, False


def fleet_phase(env, bg, results):
    """Phase 3: two services in one fleet under the generated access control; a rogue holds
    controller-1's certificate but not the fleet's secret."""
    log("phase 3: a fleet of two services, and a rogue with controller-1's certificate")
    admin = (
        "sed -i 's/^services = .*/services = [\"controller-1\", \"controller-2\"]/' fleet.toml\n"
        "mfc-deploy generate --inventory fleet.toml --out fleet\n"
        "for c in controller-1 controller-2; do\n"
        "  mfc-lab service-config --devices aero-1,aero-2 --scenario 2 --secret-file fleet.secret"
        " > fleet/services/$c/$c.service.toml\n"
        "  printf '\\n[fleet]\\nname = \"f\"\\n' >> fleet/services/$c/$c.service.toml\n"
        "done\n"
        "ssh root@10.77.0.3 install -d -m 750 /etc/mfc\n"
        "scp fleet/router/* root@10.77.0.1:/etc/mfc/\n"
        "scp fleet/services/controller-1/* root@10.77.0.2:/etc/mfc/\n"
        "scp fleet/services/controller-2/* root@10.77.0.3:/etc/mfc/\n")
    r = env.run("admin", admin)
    if not check(r.returncode == 0, "phase 3: a second service is generated, configured and copied",
                 r.stderr.strip()[-400:]):
        return False
    env.stop("controller")
    env.stop("router")
    env.start(bg["router"][0], "router", bg["router"][1])
    env.start(bg["controller"][0], "controller", bg["controller"][1])
    env.start("controller-2", "controller-2", bg["controller"][1].replace("controller-1", "controller-2"))
    # Longer than the scenario's 40 s: the faults below each wait for controller-1 to hold
    # both plants again, which may take some seconds each on a busy machine.
    for d in ["aero-1", "aero-2"]:
        env.start(bg[d][0], d, f"{bg[d][1]} --duration {FLEET_RUN}")
    t_plants = time.time()
    want = {"controller-1", "controller-2"}
    before, ok = fleet_view(env, want, 30)
    check(ok, "phase 3: both members see each other and split the 64 shards", str(before)[:400])
    owned = {x["controller_id"]: sorted(x.get("owned_shards", [])) for x in before or []}
    results["phase3_owned_shards"] = {k: len(v) for k, v in owned.items()}
    # The rogue: controller-1's certificate and zenoh config, without fleet.secret.
    intr = f"/etc/netns/{HOSTS['intruder'][0]}/mfc"
    for f in (env.work / "fleet" / "services" / "controller-1").iterdir():
        if f.name != "fleet.secret":
            shutil.copy(f, intr)
    rogue = "/etc/mfc/controller-1.json5"
    tokens = [subprocess.Popen(
        ["ip", "netns", "exec", HOSTS["intruder"][0], "zenoh-probe", "--zenoh-config", rogue,
         "token", "--key", f"mfc/v1/fleet/f/member/{name}", "--secs", "6"],
        env=env.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for name in ["controller-9", "controller-2"]]
    time.sleep(2)
    plants_running(env, "when the rogue joins")
    rc, _ = probe(env, "intruder", rogue, "put", "--key", "mfc/v1/device/aero-1/command",
                  "--count", str(FORGED), "--interval-ms", "5")
    check(rc == 0, "the rogue's session opens with controller-1's certificate, and may put commands")
    during, _ = mfcctl(env, "services")
    for t in tokens:
        t.communicate(timeout=30)
    after, ok = fleet_view(env, want, 10)
    for when, view in [("while the rogue's tokens stand", during), ("after", after)]:
        got = {x["controller_id"]: sorted(x.get("owned_shards", [])) for x in view or []}
        members = [sorted(x.get("fleet_members", [])) for x in view or []]
        check(got == owned and all(m == sorted(want) for m in members),
              f"phase 3: no member made up and no shard given up {when}",
              f"owned {({k: len(v) for k, v in got.items()})}, members {members}")
    # The operator may watch commands: what it sees of aero-1's is what anyone on the path
    # could capture, to play back into a later run (below).
    capture = subprocess.Popen(
        ["ip", "netns", "exec", HOSTS["operator"][0], "zenoh-probe", "--zenoh-config",
         "/etc/mfc/alice.json5", "sub", "--key", "mfc/v1/device/aero-1/command", "--secs", "3",
         "--save", "/etc/mfc/captured.hex"],
        env=env.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    captured_at = time.time() - t_plants
    pauses = pause_the_holder(env)
    capture.communicate(timeout=60)
    judged = 0
    for d in ["aero-1", "aero-2"]:
        rc = env.wait(d, 120)
        check(rc == 0, f"phase 3: {d} exits 0 (served by the fleet to the end)", f"exit {rc}")
        s = json.loads(Path(f"/var/lib/mfc/{d}/summary.json").read_text())
        holders = {sp.get("holder") for sp in s.get("lease", {}).get("spans", [])}
        results[f"phase3_{d}_auth"] = s.get("auth")
        results[f"phase3_{d}_holders"] = sorted(h for h in holders if h)
        check(holders and holders <= want, f"phase 3: {d} was commanded by the fleet's members only",
              str(holders))
        spans = s.get("lease", {}).get("spans", [])
        judged += judge_takeovers(d, spans, pauses, results)
        forged = s.get("auth", {}).get("forged", -1)
        want_forged = FORGED if d == "aero-1" else 0
        check(forged == want_forged,
              f"phase 3: {d} refused every forged command as unauthenticated ({want_forged})",
              f"forged {forged}")
        shutil.move(f"/var/lib/mfc/{d}", env.logs / f"phase3-{d}")
    check(judged > 0, "phase 3: the takeovers were judged on a plant controller-1 held",
          f"{judged} of 2 plants held by controller-1 before its faults")
    replay_into_later_runs(env, results, captured_at)
    return True


def replay_into_later_runs(env, results, captured_at):
    """aero-1's commands captured in phase 3 (by the operator's identity, which may watch
    them) `captured_at` s into its run, put again by the rogue (controller-1's
    certificate, which may put commands) into two later runs of aero-1: with the fleet
    up, then with it down. Each run gets the capture twice: early, when its `seq` are
    ahead of the plant's (refused as from the future), and once the plant has passed
    them, when only the run they name is wrong (refused by the lease as another run's).
    The commands are genuine (sealed with aero-1's key by a member). None may be applied;
    with the fleet down the plant must not believe it reached a controller."""
    cap = Path(f"/etc/netns/{HOSTS['operator'][0]}/mfc/captured.hex")
    lines = [l for l in cap.read_text().splitlines() if l] if cap.exists() else []
    if not check(len(lines) >= 100, "phase 3: the operator's identity captured aero-1's commands",
                 f"{len(lines)} captured in 3 s"):
        return
    shutil.copy(cap, f"/etc/netns/{HOSTS['intruder'][0]}/mfc/captured.hex")
    late = captured_at + 4.5  # the plant's time once past every captured `seq`
    Path(f"/etc/netns/{HOSTS['plant-1'][0]}/mfc/aero-1.short.toml").write_text(
        f'device = "aero-1"\nscenario = "2"\nkey_file = "aero-1.auth"\nduration = {late + 5:.1f}\n')
    out = "/var/lib/mfc/aero-1"
    for fleet in ["up", "down"]:
        if fleet == "down":
            env.stop("controller")
            env.stop("controller-2")
        t0 = time.time()
        env.start("plant-1", "aero-1", "plant-agent run --config /etc/mfc/aero-1.short.toml "
                  f"--zenoh-config /etc/mfc/aero-1.json5 --out {out}")
        puts = []
        for at in [1.5, late]:
            time.sleep(max(0.0, t0 + at - time.time()))
            puts.append(probe(env, "intruder", "/etc/mfc/controller-1.json5", "replay", "--key",
                              "mfc/v1/device/aero-1/command", "--file", "/etc/mfc/captured.hex"))
        code = env.wait("aero-1", 90)
        s = json.loads(Path(f"{out}/summary.json").read_text())
        lease = s.get("lease", {})
        other_run = lease.get("counters", {}).get("other_run", 0)
        future = s.get("counters", {}).get("future", 0)
        spans = lease.get("spans", [])
        results[f"replay_fleet_{fleet}"] = {
            "put": [o.get("put") for _, o in puts], "refused_future": future,
            "refused_other_run": other_run, "spans": spans, "exit": code,
            "auth": s.get("auth"), "controller_reached": s.get("controller_reached")}
        check(all(rc == 0 and o.get("put") == len(lines) for rc, o in puts),
              f"the rogue replays {len(lines)} captured commands twice into a later run (fleet {fleet})",
              str(puts))
        check(future >= 0.9 * len(lines) and other_run >= 0.9 * len(lines),
              f"aero-1 refused the early replays as from the future and the late ones as another run's (fleet {fleet})",
              f"future {future}, another run {other_run}, of {len(lines)} each")
        check(all(sp["holder"] in ("controller-1", "controller-2") for sp in spans),
              f"aero-1's later run was commanded by the fleet only (fleet {fleet})", str(spans)[:300])
        if fleet == "up":
            check(code == 0 and spans, "the later run was served by the fleet beside the replays",
                  f"exit {code}, spans {spans}")
        else:
            check(not spans and not s.get("controller_reached"),
                  "with the fleet down, no replayed command applied, and the plant knows it reached no controller",
                  f"spans {spans}, controller_reached {s.get('controller_reached')}")
        shutil.move(out, env.logs / f"replay-fleet-{fleet}-aero-1")


def find_alpha(cfg, channel):
    """alpha of `channel` in mfcctl's JSON configuration, wherever the law puts it."""
    chans = cfg.get("channels") or cfg.get("config", {}).get("channels") or []
    if channel >= len(chans):
        return None
    found = []

    def walk(v):
        if isinstance(v, dict):
            for k, x in v.items():
                if k == "alpha" and isinstance(x, (int, float)):
                    found.append(float(x))
                else:
                    walk(x)
        elif isinstance(v, list):
            for x in v:
                walk(x)
    walk(chans[channel])
    return found[0] if found else None


# The gateway of the guide and the plants it hosts.
GATEWAY, GATEWAY_PLANTS = "cell-1", ["aero-g1", "aero-g2"]


def gateway_plants(env, off):
    """Phase 1's gateway ran its plants beside aero-1 and aero-2, through the router, under
    its own certificate and batch key: each plant served to its end, every batch sealed and
    every command batch proved."""
    code = env.wait(GATEWAY, 120)
    check(code == 0, f"phase 1: the gateway {GATEWAY} exits 0 (a controller answered each plant)",
          f"exit {code}; log: {env.log_text(GATEWAY)[-400:]}")
    for d in GATEWAY_PLANTS:
        path = Path(f"/var/lib/mfc/{GATEWAY}/{d}/summary.json")
        if not check(path.is_file(), f"phase 1: {d} (gateway {GATEWAY}) wrote its record", str(path)):
            continue
        s = json.loads(path.read_text())
        auth = s.get("auth", {})
        results[f"phase1_{d}_rms_ratio"] = {c["name"]: c["rms"] / off[c["name"]] for c in s["channels"]}
        results[f"phase1_{d}_counters"] = s["counters"]
        check(auth.get("authenticated") is True and auth.get("forged") == 0,
              f"phase 1: {d}'s batches were sealed and every command batch proved its origin",
              str(auth))
        k = s["counters"]
        check(k["commands"] >= 0.9 * k["periods"],
              f"phase 1: {d} was commanded through the gateway in at least 90 % of its periods",
              f"{k['commands']} commands in {k['periods']} periods")
    shutil.move(f"/var/lib/mfc/{GATEWAY}", env.logs / f"phase1-{GATEWAY}")


def plants_running(env, what):
    """Checks made while both plants run are only worth something while they run."""
    running = all(env.procs[d][0].poll() is None for d in ("aero-1", "aero-2"))
    check(running, f"both plants still run {what}")


def attacks(env):
    intr = f"/etc/netns/{HOSTS['intruder'][0]}/mfc"
    # The intruder holds aero-1's bundle (a stolen plant) and the gateway's.
    shutil.copytree(env.work / "fleet" / "devices" / "aero-1", intr, dirs_exist_ok=True)
    shutil.copytree(env.work / "fleet" / "gateways" / GATEWAY, intr, dirs_exist_ok=True)
    gw = f"/etc/mfc/{GATEWAY}.json5"
    gw_batches = {g: f"mfc/v1/shard/{shard_of(g)}/gateway/{g}/samples" for g in (GATEWAY, "cell-2")}
    p = "mfc/v1/device"
    stolen = "/etc/mfc/aero-1.json5"
    # aero-1's config, giving up at once instead of retrying: the base of the direct dials
    # and of the refused identities below.
    good = client_config(f"{intr}/aero-1.json5")
    good["connect"]["timeout_ms"] = 0
    Path(f"{intr}/good.json5").write_text(json.dumps(good))
    env.dials = {}
    for host, ports in getattr(env, "plant_udp", {}).items():
        for port in ports:
            addr = HOSTS[host][1]
            env.dials[(host, addr, port)] = subprocess.Popen(
                ["ip", "netns", "exec", HOSTS["intruder"][0], "zenoh-probe", "--zenoh-config",
                 "/etc/mfc/good.json5", "--connect", f"quic/{addr}:{port}", "--open-timeout", "6",
                 "open"], env=env.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watched = [sample_key("aero-2"), f"{p}/aero-2/command", f"{p}/aero-2/reference", sample_key("aero-1")]
    # The witnesses: the operator's identity on the operator's host (it may watch samples and
    # commands), and the controller's on the controller host (the only one that receives
    # references); the control is aero-1's own sample key.
    def witness(host, config, keys):
        return subprocess.Popen(
            ["ip", "netns", "exec", HOSTS[host][0], "zenoh-probe", "--zenoh-config", config,
             "sub", "--secs", "20"] + sum([["--key", k] for k in keys], []),
            env=env.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # The operator's reference puts go under its own name (the router lets it use no other).
    named_reference = f"{p}/aero-2/reference/by/alice"
    witnesses = [witness("operator", "/etc/mfc/alice.json5", watched[:2] + watched[3:]),
                 witness("controller", "/etc/mfc/controller-1.json5",
                         watched[2:3] + [named_reference] + list(gw_batches.values()))]
    time.sleep(1.5)
    plants_running(env, "when the attacks start")
    forged = {}
    for k in watched:
        forged[k] = probe(env, "intruder", stolen, "put", "--key", k,
                          "--count", str(FORGED), "--interval-ms", "5")
    for k in watched[:3]:
        forged[k + " (delete)"] = probe(env, "intruder", stolen, "delete", "--key", k, "--count", "10")
    # The gateway's certificate: another device's keys, another gateway's batches, and (the
    # control) its own batch key, which the services' subscription does receive.
    for k in watched[:3] + list(gw_batches.values()):
        forged[k + " (gateway)"] = probe(env, "intruder", gw, "put", "--key", k,
                                         "--count", str(FORGED), "--interval-ms", "5")
    # An operator may steer and watch, never command.
    forged["operator command"] = probe(env, "operator", "/etc/mfc/alice.json5", "put", "--key",
                                       f"{p}/aero-2/command", "--count", str(FORGED),
                                       "--interval-ms", "5", "--marker", "FORGED-BY-OPERATOR")
    # The controller witness's control: the operator may put on a reference key.
    forged["operator reference"] = probe(env, "operator", "/etc/mfc/alice.json5", "put", "--key",
                                         named_reference, "--count", "10",
                                         "--interval-ms", "5", "--marker", "OPERATOR")
    # Watching: aero-2's keys must stay silent, aero-1's own command key (the control) not.
    rc_sub, seen = probe(env, "intruder", stolen, "sub", "--secs", "3", "--key", sample_key("aero-2"),
                         "--key", f"{p}/aero-2/command", "--key", f"{p}/aero-1/command")
    # Serving and announcing in aero-2's name, while the operator asks.
    fake_q = subprocess.Popen(
        ["ip", "netns", "exec", HOSTS["intruder"][0], "zenoh-probe", "--zenoh-config", stolen,
         "queryable", "--key", f"{p}/aero-2/config/**", "--secs", "5"],
        env=env.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    fake_t = subprocess.Popen(
        ["ip", "netns", "exec", HOSTS["intruder"][0], "zenoh-probe", "--zenoh-config", stolen,
         "token", "--key", "mfc/v1/alive/plant/aero-2-forged", "--secs", "5"],
        env=env.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(1.5)
    _, asked = probe(env, "operator", "/etc/mfc/alice.json5", "get", "--key",
                     f"{p}/aero-2/config/by/alice", "--count", "3")
    _, alive = probe(env, "operator", "/etc/mfc/alice.json5", "alive", "--key", "mfc/v1/alive/**")
    fake_q.communicate(timeout=30)
    fake_t.communicate(timeout=30)
    gets = {}
    for k in [f"{p}/aero-2/config", f"{p}/aero-2/status", f"{p}/aero-1/config"]:
        gets[k] = probe(env, "intruder", stolen, "get", "--key", k, "--count", "3")
    plants_running(env, "when the attacks end")
    per = {}
    w = []
    for wp in witnesses:
        out, err = wp.communicate(timeout=60)
        try:
            o = json.loads(out.strip().splitlines()[-1])
        except (json.JSONDecodeError, IndexError):
            o = {"error": out + err}
        w.append(o)
        per.update(o.get("per_key", {}))
    results["forgery"] = {"witnesses": w, "forger_sub": seen, "forger_gets": {k: v[1] for k, v in gets.items()},
                          "operator_asks_aero2_config": asked, "operator_sees_alive": alive}
    check(rc_sub == 0 and all(rc == 0 for rc, _ in forged.values()),
          "the forger's sessions open with aero-1's certificate", str(forged))
    for k in watched[:3]:
        got = per.get(k, {})
        check(got.get("marked") == 0, f"forged puts on {k} arriving: 0 (of {FORGED} with aero-1's "
              f"certificate, {FORGED} with the gateway's" + (f", {FORGED} by the operator)"
              if k.endswith("command") else ")"), str(got))
        check(got.get("deletes") == 0, f"forged deletes on {k} arriving: 0 of 10", str(got))
        real = per.get(named_reference if k.endswith("reference") else k, {})
        check(real.get("received", 0) >= 10, f"the witness does see {k}'s real traffic"
              + (" (the operator's, under its name)" if k.endswith("reference") else ""), str(real))
    ctl = per.get(watched[3], {})
    check(ctl.get("marked", 0) >= 0.9 * FORGED,
          "control: the same forger's puts on aero-1's own sample key arrive", str(ctl))
    other = per.get(gw_batches["cell-2"], {})
    check(other.get("marked") == 0,
          f"puts with {GATEWAY}'s certificate on another gateway's batch key arriving: 0 of {FORGED}",
          str(other))
    own = per.get(gw_batches[GATEWAY], {})
    check(own.get("marked", 0) >= 0.9 * FORGED,
          f"control: puts with {GATEWAY}'s certificate on its own batch key arrive", str(own))
    pk = seen.get("per_key", {})
    check(pk.get(sample_key("aero-2"), {}).get("received") == 0
          and pk.get(f"{p}/aero-2/command", {}).get("received") == 0,
          "the forger subscribed to aero-2's sample and command keys receives 0", str(seen))
    check(pk.get(f"{p}/aero-1/command", {}).get("received", 0) > 0,
          "control: the forger's subscription to aero-1's own command key receives commands", str(seen))
    for k, (rc, o) in gets.items():
        check(rc == 0 and o.get("replies") == 0 and o.get("error_replies") == 0,
              f"the forger's queries on {k} get no reply", str(o))
    check(asked.get("replies", 0) >= 1 and asked.get("marked_replies") == 0,
          "a queryable declared in aero-2's name answers nobody; the service still does", str(asked))
    names = alive.get("alive", [])
    check("mfc/v1/alive/plant/aero-1" in names and not any("forged" in n for n in names),
          "a liveliness token forged in aero-2's name is not seen; the real ones are", str(names))

    # Refused identities: variants of `good` (aero-1's config, giving up at once).
    nocert = json.loads(json.dumps(good))
    tls = nocert["transport"]["link"]["tls"]
    tls["enable_mtls"] = False
    del tls["connect_certificate"], tls["connect_private_key"]
    Path(f"{intr}/nocert.json5").write_text(json.dumps(nocert))
    r = env.run("admin", "mfc-deploy generate --inventory fleet.toml --out otherfleet")
    check(r.returncode == 0, "a second, foreign fleet is generated", r.stderr[-300:])
    shutil.copy(env.work / "otherfleet/devices/aero-1/aero-1.pem", f"{intr}/foreign.pem")
    shutil.copy(env.work / "otherfleet/devices/aero-1/aero-1.key", f"{intr}/foreign.key")
    foreign = json.loads(json.dumps(good))
    foreign["transport"]["link"]["tls"]["connect_certificate"] = "/etc/mfc/foreign.pem"
    foreign["transport"]["link"]["tls"]["connect_private_key"] = "/etc/mfc/foreign.key"
    Path(f"{intr}/foreign.json5").write_text(json.dumps(foreign))
    # A name the router's certificate does not carry: this host resolves it to the router.
    Path(f"/etc/netns/{HOSTS['intruder'][0]}/hosts").write_text(
        f"127.0.0.1 localhost\n{HOSTS['router'][1]} not-the-router\n")
    refused = {}
    for name, cfg, extra in [
        ("control: aero-1's own certificate", "/etc/mfc/good.json5", []),
        ("the router dialled by a name not in its certificate", "/etc/mfc/good.json5",
         ["--connect", "quic/not-the-router:7447"]),
        ("no client certificate", "/etc/mfc/nocert.json5", []),
        ("a certificate from another CA", "/etc/mfc/foreign.json5", []),
        ("plain TCP", None, ["--mode", "client", "--connect", "tcp/10.77.0.1:7447", "--no-multicast-scouting"]),
    ]:
        rc, o = probe(env, "intruder", cfg, *extra, "--open-timeout", "8", "open")
        refused[name] = {"exit": rc, **o}
        if name.startswith("control"):
            check(rc == 0, f"{name} opens a session", str(o))
        else:
            check(rc != 0, f"{name} is refused", str(o))
    # Around the router: a client with a valid certificate dialled each plant's own UDP
    # port, while the plants ran (started with the attacks, collected here).
    for (host, addr, port), dial in env.dials.items():
        out, _ = dial.communicate(timeout=60)
        try:
            o = json.loads(out.strip().splitlines()[-1])
        except (json.JSONDecodeError, IndexError):
            o = {"raw": out}
        refused[f"{host} direct quic/{addr}:{port}"] = {"exit": dial.returncode, **o}
        check(dial.returncode != 0, f"{host} cannot be reached directly (quic/{addr}:{port})", str(o))
    check(len(env.dials) >= 2, "control: the plants' own UDP ports were found and dialled")
    results["refused"] = refused



# ---------------------------------------------------------------- phase 4

# Phase 4's zenoh port: every process is a peer, members listen on their own host.
PEER_PORT = 7448
# The plants' run in phase 4 (s): long enough for the start, a change, the partition, the
# heal and the survivor's run to the end.
PEER_RUN = 55.0
# How long the members are cut from each other: well past the links' lease (3 s), so each
# sees the other leave and takes every shard in its own view, as in the report.
PARTITION = 10.0


def peer_config(listen, connect, operator=False):
    """A peer's zenoh config: listen on `listen` (a member), dial `connect` (retrying for
    ever, but an operator's `open` gives up waiting after 3 s), no scouting, the guide's
    link lease and real-time queue. Plain TCP: the deployment's certificates are client
    certificates for the router; what this phase tests is the lease and the proofs of
    origin, which ride on every message whatever the link."""
    return {
        "mode": "peer",
        "listen": {"endpoints": [f"tcp/{listen}:{PEER_PORT}"] if listen else []},
        "connect": {"endpoints": [f"tcp/{a}:{PEER_PORT}" for a in connect],
                    "timeout_ms": 3000 if operator else -1, "exit_on_failure": False,
                    "retry": {"period_init_ms": 250, "period_max_ms": 1000,
                              "period_increase_factor": 2}},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tx": {"lease": 3000, "queue": {"size": {"real_time": 16}}}}},
    }


def isolate_members(on):
    """Bridge port isolation: the two members' ports stop forwarding to each other, and
    only to each other; the plants and the operator still reach both."""
    for host in ["controller", "controller-2"]:
        port = f"mfcsw{list(HOSTS).index(host)}"
        sh(["ip", "-n", SWITCH, "link", "set", "dev", port, "type", "bridge_slave",
            "isolated", "on" if on else "off"])


def lease_of(env, device):
    st, err = mfcctl(env, "status", device)
    return (st.get("lease_holder"), int(st.get("lease_epoch", 0))) if st else (None, err)


def wait_leases(env, plants, ok, timeout):
    """Until `ok(lease)` holds for every plant's (holder, epoch); (done, the last seen)."""
    deadline, last = time.time() + timeout, None
    while time.time() < deadline:
        last = {d: lease_of(env, d) for d in plants}
        if all(ok(x) for x in last.values()):
            return True, last
        time.sleep(1)
    return False, last


def stable_holder(env, device, timeout):
    """The plant's lease holder once two reads 2 s apart agree (a plant first claimed by a
    member that is not its preferred one is handed over in its first seconds)."""
    deadline, seen = time.time() + timeout, None
    while time.time() < deadline:
        now = lease_of(env, device)
        if now[0] and now == seen:
            return now
        seen = now
        time.sleep(2)
    return None


def set_alpha(env, device, channel, value):
    """`mfcctl set` on the operator's host: (acknowledged, who holds it, stderr)."""
    r = env.run("operator", f"mfcctl --zenoh-config {env.op_config} --key-file /etc/mfc/alice.auth"
                f" --json set {device} --channel {channel} alpha={value!r}", timeout=30)
    if r.returncode != 0:
        return False, [], r.stderr.strip()
    return True, json.loads(r.stdout).get("held_by", []), ""


def kill_at_join(env, victim, other, t_heal):
    """SIGKILL `victim` the moment its log says `other` joined its view again (after the
    heal): the members are exchanging the shards the partition gave both. Returns the
    seconds from the heal to the kill, or None if the join never came."""
    path, offset = env.procs[victim][4], Path(env.procs[victim][4]).stat().st_size
    deadline = time.time() + 30
    while time.time() < deadline:
        with open(path, errors="replace") as f:
            f.seek(offset)
            new = f.read()
        if any("fleet member joined" in l and f"member={other}" in l for l in new.splitlines()):
            env.procs[victim][0].send_signal(signal.SIGKILL)
            return time.time() - t_heal
        time.sleep(0.01)
    return None


def peer_phase(env, results):
    """Phase 4: no router, every process a zenoh peer; the plants and the operator reach
    both members, and the members are cut from each other. The partition must move no
    plant and acknowledge no change; the holder killed as the members meet again must be
    replaced, with every acknowledged change."""
    log("phase 4: peers, no router; the plants reach both members, then the members are cut off from each other")
    for name in ["controller", "controller-2", "router"]:
        env.stop(name)
    c1, c2 = HOSTS["controller"][1], HOSTS["controller-2"][1]
    configs = {"controller": peer_config(c1, []), "controller-2": peer_config(c2, [c1]),
               "plant-1": peer_config(None, [c1, c2]), "plant-2": peer_config(None, [c1, c2]),
               "operator": peer_config(None, [c1, c2], operator=True)}
    for host, cfg in configs.items():
        Path(f"/etc/netns/{HOSTS[host][0]}/mfc/peer.json5").write_text(json.dumps(cfg, indent=2))
    plants = {"aero-1": "plant-1", "aero-2": "plant-2"}
    for d, host in plants.items():
        Path(f"/etc/netns/{HOSTS[host][0]}/mfc/{d}.peer.toml").write_text(
            f'device = "{d}"\nscenario = "2"\nkey_file = "{d}.auth"\nduration = {PEER_RUN}\n')
    env.op_config = "/etc/mfc/peer.json5"
    procs = {"controller-1": "controller", "controller-2": "controller-2"}
    for cid, name in procs.items():
        env.start(name, name, f"controller-service --controller-id {cid} --config "
                  f"/etc/mfc/{cid}.service.toml --zenoh-config /etc/mfc/peer.json5")
    want = set(procs)
    _, ok = fleet_view(env, want, 30)
    if not check(ok, "phase 4: the members, peers, see each other and split the shards"):
        return
    for d, host in plants.items():
        env.start(host, d, f"plant-agent run --config /etc/mfc/{d}.peer.toml --zenoh-config "
                  f"/etc/mfc/peer.json5 --out /var/lib/mfc/{d}")
    # The plants' liveliness tokens reach the members, not the operator (peers do not
    # forward): a plant is served when its status names a lease holder.
    ok, last = wait_leases(env, plants, lambda lease: bool(lease[0]), 30)
    check(ok, "phase 4: both plants served, through no router", str(last))
    held = stable_holder(env, "aero-1", 20)
    if not check(held is not None, "phase 4: aero-1's lease has a holder", str(held)):
        return
    holder, epoch = held
    other = next(c for c in want if c != holder)
    results["phase4_aero1_holder"] = held
    cfg, err = mfcctl(env, "config", "aero-1")
    alpha = find_alpha(cfg, 0) if cfg else None
    if not check(alpha is not None, "phase 4: the operator reads aero-1's alpha", err or ""):
        return
    # Each plant: the alpha acknowledged last, and every value sent after it (a change
    # not acknowledged may still be in force: the survivor may show it, or the one before).
    acked, sent = {}, {}
    for d, factor in [("aero-1", 1.01), ("aero-2", 1.03)]:
        a = alpha * factor
        ok, by, err = set_alpha(env, d, 0, a)
        check(ok and sorted(by) == sorted(want),
              f"phase 4: a change of {d} is acknowledged once both members hold it (held_by names both)",
              f"acknowledged {ok}, held by {by}: {err}")
        if ok:
            acked[d], sent[d] = a, [a]

    plants_running(env, "before the members are cut off from each other")
    isolate_members(True)
    t_cut = time.time()
    log(f"members isolated from each other for {PARTITION:.0f} s; {holder} holds aero-1 (epoch {epoch})")
    alone, leases = False, []
    while time.time() < t_cut + PARTITION:
        view, _ = mfcctl(env, "services")
        members = sorted(sorted(x.get("fleet_members", [])) for x in view or [])
        alone = alone or members == [[c] for c in sorted(want)]
        leases.append(lease_of(env, "aero-1"))
        time.sleep(1)
    check(alone, "phase 4: the partition is real: each member saw only itself", str(members))
    b = alpha * 1.02
    ok_b, by_b, err_b = set_alpha(env, "aero-1", 0, b)
    results["phase4_change_during_partition"] = {"acknowledged": ok_b, "held_by": by_b, "reason": err_b}
    check(not ok_b and "not acknowledged" in err_b,
          "phase 4: a change while the partner is cut off is not acknowledged, and the reply says why",
          f"acknowledged {ok_b}, held by {by_b}: {err_b[-300:]}")
    sent.setdefault("aero-1", []).append(b)
    if ok_b:
        acked["aero-1"], sent["aero-1"] = b, [b]
    # A read that got no answer (a slow query on a busy host) says nothing either way; most
    # must answer, and every answer must name the same holder. Not the same epoch: the
    # plant's lease lapses whenever its holder is silent for 3 periods (30 ms, a stall a
    # loaded host gives now and then), and the holder, still preferred and in step,
    # claims it back at once under the next epoch. The plant's own record, read at the
    # end, says every lease up to the last epoch read here was the holder's.
    answered = [x for x in leases if x[0] is not None]
    moved = [x for x in answered if x[0] != holder]
    epochs = [x[1] for x in answered]
    results["phase4_leases_during_partition"] = leases
    check(len(answered) >= len(leases) // 2 and not moved and epochs == sorted(epochs),
          f"phase 4: the partition moved no plant (aero-1 stayed with {holder}, epochs only up)",
          f"{len(answered)} of {len(leases)} reads answered; epochs {epochs}; "
          f"other holders seen: {str(moved)[:300]}")
    last_epoch = max(epochs, default=epoch)
    plants_running(env, "when the partition heals")
    isolate_members(False)
    t_heal = time.time()
    secs = kill_at_join(env, procs[holder], other, t_heal)
    results["phase4_kill_after_heal_s"] = secs
    if not check(secs is not None, f"phase 4: {holder} saw {other} join again after the heal, and was killed then"):
        return
    log(f"SIGKILL {holder} {secs:.3f} s after the heal, as it saw {other} join again")
    ok, last = wait_leases(env, plants, lambda lease: lease[0] == other, 30)
    check(ok, f"phase 4: {other} holds both plants' leases after the kill", str(last))
    survivor = {}
    for d, v in acked.items():
        cfg, err = mfcctl(env, "config", d)
        got = find_alpha(cfg, 0) if cfg else None
        survivor[d] = got
        check(got is not None and any(abs(got - x) <= 1e-9 * abs(x) for x in sent[d]),
              f"phase 4: the change acknowledged last on {d} (or one sent after it) is in force on {other}",
              f"alpha {got}; acknowledged {v}, sent since {sent[d][1:]}, before {alpha}")
    results["phase4_acknowledged"] = acked
    results["phase4_survivor_alpha"] = survivor
    check(len(acked) == len(plants), "phase 4: an acknowledged change on each plant was there to be lost")
    for d in plants:
        rc = env.wait(d, 120)
        check(rc == 0, f"phase 4: {d} exits 0 (served to the end)", f"exit {rc}")
        s = json.loads(Path(f"/var/lib/mfc/{d}/summary.json").read_text())
        spans = s.get("lease", {}).get("spans", [])
        one_holder_at_a_time("phase 4", d, spans)
        if d == "aero-1":
            during = [(sp["holder"], sp["epoch"]) for sp in spans if sp["epoch"] <= last_epoch]
            check(during and all(h == holder for h, _ in during),
                  f"phase 4: aero-1's own record: every lease up to epoch {last_epoch} (the last "
                  f"read in the partition) was {holder}'s", str(during))
            results["phase4_aero-1_reclaims_in_partition"] = len(during) - 1
        results[f"phase4_{d}_spans"] = [(sp["holder"], sp["epoch"], sp["first"], sp["last"]) for sp in spans]
        results[f"phase4_{d}_auth"] = s.get("auth")
        check(s.get("auth", {}).get("forged") == 0, f"phase 4: {d} got no command it refused as forged",
              str(s.get("auth")))
        gone = [i for i, sp in enumerate(spans) if sp["holder"] == holder]
        if gone and gone[-1] + 1 < len(spans):
            nxt = spans[gone[-1] + 1]
            results[f"phase4_{d}_takeover_periods"] = [nxt["first"] - spans[gone[-1]]["last"]]
        check(spans and spans[-1]["holder"] == other, f"phase 4: {d} ended with {other}", str(spans[-1:]))
        shutil.move(f"/var/lib/mfc/{d}", env.logs / f"phase4-{d}")


def takeover_figures(results):
    """Every takeover the plants recorded (phases 3 and 4), in periods of 10 ms: p50, p99,
    max. Reported, not judged: a time on a shared 2-core machine is a measurement."""
    all_ = sorted(x for k, v in results.items() if k.endswith("_takeover_periods") for x in v)
    if not all_:
        return
    pick = lambda q: all_[min(len(all_) - 1, math.ceil(q * len(all_)) - 1)]
    results["takeover_periods"] = {"n": len(all_), "p50": pick(0.5), "p99": pick(0.99), "max": all_[-1]}
    log(f"takeovers after the holder's silence, in 10 ms periods: {results['takeover_periods']}")


if __name__ == "__main__":
    main()
