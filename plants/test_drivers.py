"""Tests of the Python plant drivers' shared serve loop (driver_loop.py) and of every driver
that uses it: each refuses the same bad requests with the same answers, and changes nothing
when it does, so the drivers cannot drift apart again.

Standard library only: `python3 plants/test_drivers.py` (run by the Rust test
tests/tests/python_drivers.rs, so `cargo test` runs it).
"""

import io
import os
import subprocess
import sys
import tempfile
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.dont_write_bytecode = True
sys.path.insert(0, HERE)
import driver_loop  # noqa: E402
from driver_loop import MAX_ADVANCE, MAX_CHANNELS, MAX_LINE  # noqa: E402

# (name, argv after python3, channels)
DRIVERS = [
    ("heater", ["heater/heater.py", "--seed", "3"], 1),
    ("dc-motor", ["dc-motor/dc_motor.py", "--seed", "3", "--noise", "0.001"], 1),
    ("coupled-lags, 1 channel", ["coupled-lags/coupled_lags.py", "--channels", "1"], 1),
    ("coupled-lags, 3 channels", ["coupled-lags/coupled_lags.py", "--seed", "3"], 3),
]


def good_requests(n):
    """A session's worth of valid requests for an n-channel driver (stop excluded)."""
    return [
        "read",
        "write " + " ".join(f"{1.5 - i:e}" for i in range(n)),
        "advance 0.5",
        "read",
        "write " + " ".join(["7"] * n),
        "advance 1.25e0",
        "read",
        "advance 0",
        "read",
    ]


def bad_requests(n):
    """Requests every driver must refuse, each with its exact answer."""
    ones = ["1"] * n
    need = f"err advance needs one finite duration in 0 ..= {MAX_ADVANCE:g} (s)"
    return [
        (f"advance {MAX_ADVANCE * 2:g}", need),
        (f"advance {MAX_ADVANCE + 1e-9!r}", need),
        ("advance -1", need),
        ("advance nan", need),
        ("advance inf", need),
        ("advance 1e999", need),
        ("advance", need),
        ("advance 1 2", need),
        ("advance 0x10", need),
        ("write " + " ".join(["nan"] * n), "err write: not a finite number: 'nan'"),
        ("write " + " ".join(ones[1:] + ["-inf"]), "err write: not a finite number: '-inf'"),
        ("write " + " ".join(ones[1:] + ["1e400"]), "err write: not a finite number: '1e400'"),
        ("write " + " ".join(["1_0"] + ones[1:]), "err write: not a finite number: '1_0'"),
        ("write " + " ".join(ones + ["1"]), f"err write needs {n} number(s), got {n + 1}"),
        ("write " + " ".join(ones[1:]), f"err write needs {n} number(s), got {n - 1}"),
        ("read now", "err read takes no arguments"),
        ("stop now", "err stop takes no arguments"),
        ("fly", "err unknown request 'fly'"),
        ("READ", "err unknown request 'READ'"),
        ("", "err unknown request ''"),
        ("x" * (MAX_LINE + 100), f"err request longer than {MAX_LINE} characters"),
    ]


def session(argv, requests):
    """Run a driver from a foreign working directory on `requests` (then end of input) and
    return its answers, exit status and stderr."""
    with tempfile.TemporaryDirectory() as cwd:
        p = subprocess.run(
            [sys.executable] + [os.path.join(HERE, argv[0])] + argv[1:],
            input="".join(r + "\n" for r in requests),
            capture_output=True,
            text=True,
            cwd=cwd,
            timeout=60,
        )
    return p.stdout.splitlines(), p.returncode, p.stderr


class Drivers(unittest.TestCase):
    def test_every_driver_refuses_bad_requests_alike_and_changes_nothing(self):
        for name, argv, n in DRIVERS:
            with self.subTest(driver=name):
                good = good_requests(n)
                bad = bad_requests(n)
                # Every bad request before every good one: the good answers must not move.
                requests, expected = [], {}
                for g in good:
                    for b, answer in bad:
                        expected[len(requests)] = answer
                        requests.append(b)
                    requests.append(g)
                requests.append("stop")
                answers, status, err = session(argv, requests)
                self.assertEqual((status, err), (0, ""))
                self.assertEqual(answers[0], f"hello channels={n}")
                answers = answers[1:]
                self.assertEqual(len(answers), len(requests), answers[-5:])
                for i, want in expected.items():
                    self.assertEqual(answers[i], want, f"request {requests[i][:60]!r}")
                self.assertEqual(answers[-1], "ok", "stop")
                clean, status, err = session(argv, good + ["stop"])
                self.assertEqual((status, err), (0, ""))
                good_answers = [a for i, a in enumerate(answers[:-1]) if i not in expected]
                self.assertEqual(good_answers, clean[1:-1], "the refusals changed something")
                # The good answers are what they claim: reads give n numbers, writes `ok`.
                for r, a in zip(good, good_answers):
                    words = a.split()
                    if r == "read":
                        self.assertEqual(len(words), n, a)
                    elif r.startswith("write"):
                        self.assertEqual((words[0], len(words)), ("ok", n + 1), a)
                    else:
                        self.assertEqual(a, "ok")

    def test_end_of_input_ends_every_driver_cleanly(self):
        for name, argv, n in DRIVERS:
            with self.subTest(driver=name):
                answers, status, err = session(argv, ["write " + " ".join(["3"] * n)])
                self.assertEqual((status, err), (0, ""))
                self.assertEqual(len(answers), 2, answers)
                self.assertTrue(answers[1].startswith("ok "), answers)


class FakeModel:
    """A model that records what the loop asked of it."""

    def __init__(self, channels, outputs=None):
        self.channels = channels
        self.outputs = outputs if outputs is not None else [0.5] * channels
        self.calls = []

    def read(self):
        self.calls.append("read")
        return self.outputs

    def write(self, values):
        self.calls.append(("write", values))
        return values

    def advance(self, dt):
        self.calls.append(("advance", dt))

    def safe_stop(self):
        self.calls.append("safe_stop")


def serve(model, channels, text):
    out = io.StringIO()
    status = driver_loop.serve(model, channels, io.StringIO(text), out)
    return status, out.getvalue().splitlines()


class Loop(unittest.TestCase):
    def test_the_limits_are_inclusive(self):
        m = FakeModel(1)
        status, answers = serve(m, 1, f"advance {MAX_ADVANCE:g}\nadvance 0\nstop\n")
        self.assertEqual((status, answers), (0, ["hello channels=1", "ok", "ok", "ok"]))
        self.assertEqual(m.calls, [("advance", MAX_ADVANCE), ("advance", 0.0), "safe_stop"])
        longest = "write " + "0" * (MAX_LINE - len("write 1")) + "1"
        self.assertEqual(len(longest), MAX_LINE)
        _, answers = serve(FakeModel(1), 1, longest + "\n" + "x" + longest + "\n")
        self.assertEqual(answers[1:], ["ok 1.0", f"err request longer than {MAX_LINE} characters"])

    def test_an_overlong_line_is_refused_whole_and_serving_goes_on(self):
        m = FakeModel(2)
        text = "write 1 " + "2" * (3 * MAX_LINE) + "\nwrite 1 2\n"
        _, answers = serve(m, 2, text)
        self.assertEqual(
            answers,
            ["hello channels=2", f"err request longer than {MAX_LINE} characters", "ok 1.0 2.0"],
        )
        self.assertEqual(m.calls, [("write", [1.0, 2.0]), "safe_stop"])

    def test_an_overlong_last_line_is_the_end_of_input(self):
        m = FakeModel(1)
        _, answers = serve(m, 1, "write 1\n" + "x" * (2 * MAX_LINE))
        self.assertEqual(answers, ["hello channels=1", "ok 1.0"])
        self.assertEqual(m.calls[-1], "safe_stop")

    def test_refused_requests_never_reach_the_model(self):
        m = FakeModel(2)
        text = "".join(b + "\n" for b, _ in bad_requests(2))
        _, answers = serve(m, 2, text)
        self.assertTrue(all(a.startswith("err ") for a in answers[1:]), answers)
        self.assertEqual(m.calls, ["safe_stop"])

    def test_a_model_giving_non_finite_or_too_few_numbers_is_reported(self):
        for outputs in ([float("nan"), 1.0], [float("inf"), 1.0], [1.0], [1.0, 2.0, 3.0]):
            with self.subTest(outputs=outputs):
                _, answers = serve(FakeModel(2, outputs), 2, "read\n")
                self.assertTrue(answers[1].startswith("err read: the model gave"), answers)
                self.assertIn("not 2 finite numbers", answers[1])

    def test_channel_counts_outside_the_protocol_are_refused(self):
        for n in (0, MAX_CHANNELS + 1):
            with self.subTest(channels=n):
                with self.assertRaises(ValueError):
                    serve(FakeModel(1), n, "")
        status, answers = serve(FakeModel(MAX_CHANNELS), MAX_CHANNELS, "")
        self.assertEqual((status, answers), (0, [f"hello channels={MAX_CHANNELS}"]))

    def test_the_longest_write_fits_in_a_line(self):
        # 64 channels at full precision, as the agent writes them (`{:e}`), fit MAX_LINE.
        worst = "write " + " ".join(["-2.2250738585072014e-308"] * MAX_CHANNELS)
        self.assertLess(len(worst), MAX_LINE // 2)
        m = FakeModel(MAX_CHANNELS)
        _, answers = serve(m, MAX_CHANNELS, worst + "\n")
        self.assertTrue(answers[1].startswith("ok -2.2250738585072014e-308 "), answers[1][:80])


if __name__ == "__main__":
    unittest.main()
