//! Cost of one control step of one channel (law + output map), in ns.
//!
//! `cargo bench -p mfc`. Each benchmark steps a warmed-up channel on a synthetic signal
//! (computed beforehand, so that the figure is the step's and the ratio of two laws is the
//! ratio of their costs); the window sweep shows the cost does not grow with the window
//! (running moment sums); `estimator` is the iP's estimator alone.

use divan::{black_box, Bencher};
use mfc::{
    AdrcParams, Channel, ChannelConfig, ControllerKind, LawConfig, Order, OutputMapConfig,
    PidParams, Reference,
};

fn main() {
    divan::main();
}

/// Samples of the synthetic signal, repeated (a power of two, so the modulo is a mask).
const SIGNAL: usize = 4096;

/// The synthetic output, computed beforehand: a sine alone costs about half a PID step,
/// and the figures are the step's.
fn signal() -> Vec<f64> {
    (0..SIGNAL)
        .map(|k| {
            let t = k as f64 * 0.01;
            (t * 1.7).sin() * 0.3 + 0.001 * ((k * 7919) % 17) as f64
        })
        .collect()
}

fn intelligent(kind: ControllerKind, order: Order, window: usize) -> LawConfig {
    LawConfig::intelligent(kind, order, 2.0, [5.0, 1.0, 0.5], window)
}

/// Bench `step(t, y)` on the signal, after 1000 steps of warm-up.
fn drive<R>(bencher: Bencher, mut step: impl FnMut(f64, f64) -> R) {
    let signal = signal();
    let mut k = 0usize;
    let mut next = move || {
        let t = k as f64 * 0.01;
        let y = signal[k % SIGNAL];
        k += 1;
        step(black_box(t), black_box(y))
    };
    for _ in 0..1000 {
        next();
    }
    bencher.bench_local(next);
}

fn bench_law(bencher: Bencher, law: LawConfig) {
    let mut ch: Channel = Channel::new(&ChannelConfig {
        law,
        output: OutputMapConfig::AERO,
    })
    .unwrap();
    let r = Reference {
        y: 0.2,
        dy: 0.0,
        ddy: 0.0,
    };
    drive(bencher, move |t, y| ch.step(t, y, &r).unwrap());
}

#[divan::bench]
fn ip(b: Bencher) {
    bench_law(b, intelligent(ControllerKind::P, Order::One, 10));
}

#[divan::bench]
fn ipi(b: Bencher) {
    bench_law(b, intelligent(ControllerKind::PI, Order::One, 10));
}

#[divan::bench]
fn ipd(b: Bencher) {
    bench_law(b, intelligent(ControllerKind::PD, Order::Two, 10));
}

#[divan::bench]
fn pid(b: Bencher) {
    bench_law(
        b,
        LawConfig::Pid {
            params: PidParams {
                kp: 5.0,
                ki: 2.0,
                kd: 0.1,
                ..Default::default()
            },
        },
    );
}

#[divan::bench]
fn adrc(b: Bencher) {
    bench_law(
        b,
        LawConfig::Adrc {
            params: AdrcParams::default(),
        },
    );
}

#[divan::bench(args = [10, 50, 200])]
fn ip_window(b: Bencher, window: usize) {
    bench_law(b, intelligent(ControllerKind::P, Order::One, window));
}

/// The iP's estimator alone (a sample in, an estimate out), window 10: the part of the iP's
/// step the PID has no counterpart for, to set the iP's cost against.
#[divan::bench]
fn estimator(b: Bencher) {
    let mut e: mfc::Estimator = mfc::Estimator::new(
        mfc::EstimatorConfig {
            window: 10,
            ..Default::default()
        },
        Order::One,
    )
    .unwrap();
    drive(b, move |t, y| {
        e.push(t, y, black_box(0.3)).unwrap();
        e.estimate(Order::One).ok()
    });
}
