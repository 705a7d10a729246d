//! A control step allocates nothing: a service steps thousands of channels per
//! millisecond, and an allocation there is a lock, a page fault or a free on another thread.
//! Every law and estimator is stepped through its warm-up, its window and a gap while a
//! counting allocator watches this thread (the only test in this binary, so nothing else
//! allocates on it meanwhile).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicUsize, Ordering};

use mfc::{
    AdrcParams, Channel, ChannelConfig, ControllerKind, EstimatorConfig, EstimatorKind,
    IntelligentParams, LawConfig, Order, OutputMapConfig, PidParams, Reference,
};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    static WATCHED: Cell<bool> = const { Cell::new(false) };
}

// SAFETY: every call goes to `System` unchanged; the counter only observes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if WATCHED.with(Cell::get) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if WATCHED.with(Cell::get) {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Allocations made by `f` on this thread.
fn allocations(f: impl FnOnce()) -> usize {
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    WATCHED.with(|w| w.set(true));
    f();
    WATCHED.with(|w| w.set(false));
    ALLOCATIONS.load(Ordering::Relaxed) - before
}

fn laws() -> Vec<(&'static str, LawConfig)> {
    let intelligent = |kind, order, kind_of_estimator, filter| LawConfig::Intelligent {
        params: IntelligentParams {
            kind,
            order,
            alpha: 2.0,
            kp: 5.0,
            ki: 1.0,
            kd: 0.5,
            estimate_filter: filter,
            hold_estimate_filter: filter,
            derivative_observer: if order == Order::Two { 20.0 } else { 0.0 },
            hold_band: 0.1,
            ..IntelligentParams::default()
        },
        estimator: EstimatorConfig {
            window: 20,
            kind: kind_of_estimator,
            // The gap below restarts the window.
            max_interval: 0.5,
            ..EstimatorConfig::default()
        },
    };
    let low_pass = EstimatorKind::LowPass {
        time_constant: 0.05,
    };
    vec![
        (
            "iP",
            intelligent(ControllerKind::P, Order::One, EstimatorKind::Algebraic, 0.0),
        ),
        (
            "iPI",
            intelligent(
                ControllerKind::PI,
                Order::One,
                EstimatorKind::Algebraic,
                0.1,
            ),
        ),
        (
            "iPD",
            intelligent(
                ControllerKind::PD,
                Order::Two,
                EstimatorKind::Algebraic,
                0.1,
            ),
        ),
        (
            "iP closed loop",
            intelligent(
                ControllerKind::P,
                Order::One,
                EstimatorKind::ClosedLoop,
                0.0,
            ),
        ),
        (
            "iPD low-pass",
            intelligent(ControllerKind::PD, Order::Two, low_pass, 0.0),
        ),
        (
            "PID",
            LawConfig::Pid {
                params: PidParams {
                    kp: 5.0,
                    ki: 2.0,
                    kd: 0.1,
                    ..Default::default()
                },
            },
        ),
        (
            "ADRC",
            LawConfig::Adrc {
                params: AdrcParams::default(),
            },
        ),
    ]
}

#[test]
fn a_step_allocates_nothing() {
    // The counter sees what it should.
    let seen = allocations(|| drop(std::hint::black_box(Vec::<u8>::with_capacity(8))));
    assert_eq!(seen, 1, "the counting allocator missed an allocation");
    for (name, law) in laws() {
        let mut ch: Channel = Channel::new(&ChannelConfig {
            law,
            output: OutputMapConfig::AERO,
        })
        .unwrap();
        let mut plan = [0.0; 8];
        let refs = [Reference {
            y: 0.2,
            dy: 0.0,
            ddy: 0.0,
        }; 8];
        let mut restarted = false;
        let n = allocations(|| {
            for k in 0..5_000u32 {
                // A gap of a second at k = 2500 restarts the window.
                let t = f64::from(k) * 0.01 + if k >= 2_500 { 1.0 } else { 0.0 };
                let y = (t * 1.7).sin() * 0.3;
                let r = Reference {
                    y: if k < 1_000 { 0.2 } else { 0.1 },
                    dy: 0.0,
                    ddy: 0.0,
                };
                let out = ch.step(t, y, &r).unwrap();
                if k == 2_500 {
                    restarted = out.warming_up;
                }
                ch.plan(&out, 0.01, &refs, &[], mfc::Trend::default(), &mut plan);
                ch.report_applied(out.v * 0.9).unwrap();
            }
        });
        assert_eq!(n, 0, "{name}: {n} allocations in 5000 steps");
        // The intelligent laws' windows did restart at the gap (the path was taken).
        assert_eq!(restarted, name.starts_with('i'), "{name}");
    }
}
