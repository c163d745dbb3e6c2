//! The device-thread channel of the vendored cubecl-common (`vendor/README.md`): a task submitted without a
//! flush runs even when fewer than a buffer's worth follow it, and tasks submitted while the device thread
//! closes partial buffers run once each, in order.

use cubecl_common::device::{DeviceId, DeviceService, ServerUtilitiesHandle};
use cubecl_common::device_handle::DeviceHandle;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A service keeping the tasks' marks in order.
struct Log {
    marks: Vec<usize>,
}

impl DeviceService for Log {
    fn init(_: DeviceId) -> Self {
        Self { marks: Vec::new() }
    }

    fn utilities(&self) -> ServerUtilitiesHandle {
        Arc::new(())
    }
}

/// A device id no other test uses (one runner thread per id and stage).
fn device(index_id: u16) -> DeviceId {
    DeviceId {
        type_id: 4_242,
        index_id,
    }
}

#[test]
fn a_lone_task_runs_without_a_flush() {
    static RAN: AtomicUsize = AtomicUsize::new(0);
    let handle = DeviceHandle::<Log>::new(device(0));
    handle.submit(|_| {
        RAN.fetch_add(1, Ordering::SeqCst);
    });
    // Upstream runs it only after 31 more tasks or a blocking call; the device thread now closes a partial
    // buffer once idle.
    let start = Instant::now();
    while RAN.load(Ordering::SeqCst) == 0 && start.elapsed() < Duration::from_secs(5) {
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!(RAN.load(Ordering::SeqCst), 1, "the task did not run within 5 s");
}

#[test]
fn tasks_run_once_each_in_order_across_partial_buffers() {
    let handle = DeviceHandle::<Log>::new(device(1));
    let seen = Arc::new(Mutex::new(Vec::new()));
    for i in 0..2_000usize {
        handle.submit(move |log| log.marks.push(i));
        // Pauses of varying length let the device thread close buffers at every fill level.
        if i % 7 == 0 {
            std::thread::sleep(Duration::from_micros((i % 50) as u64));
        }
    }
    let out = seen.clone();
    handle
        .submit_blocking(move |log| *out.lock().unwrap() = std::mem::take(&mut log.marks))
        .unwrap();
    let marks = seen.lock().unwrap().clone();
    assert_eq!(marks, (0..2_000).collect::<Vec<_>>());
}
