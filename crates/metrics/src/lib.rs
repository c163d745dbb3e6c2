//! Training metrics for umgen.
//!
//! [`EventWriter`] writes TensorBoard event files (scalars), readable by TensorBoard and by
//! [`read_scalars`]. [`MetricLog`] fans one set of scalars out to TensorBoard and a JSON-lines file
//! (`metrics.jsonl`, one object per step) so that runs can be compared without TensorBoard.

mod tfevents;

pub use tfevents::{EventWriter, read_scalars};

use std::io::Write;
use std::path::Path;

/// Scalars of one run, written to `<dir>/tb/events.out.tfevents.*` and `<dir>/metrics.jsonl`.
#[derive(Debug)]
pub struct MetricLog {
    events: EventWriter,
    jsonl: std::io::BufWriter<std::fs::File>,
}

impl MetricLog {
    /// Opens the log of a run directory (appending to an existing `metrics.jsonl`, so resumed runs keep
    /// one history).
    pub fn open(dir: &Path) -> std::io::Result<Self> {
        let events = EventWriter::create(&dir.join("tb"))?;
        let f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join("metrics.jsonl"))?;
        Ok(Self {
            events,
            jsonl: std::io::BufWriter::new(f),
        })
    }

    /// Records scalars at a step.
    pub fn log(&mut self, step: u64, values: &[(&str, f64)]) -> std::io::Result<()> {
        self.events.scalars(step, values)?;
        let mut obj = serde_json::Map::new();
        obj.insert("step".into(), step.into());
        for (k, v) in values {
            obj.insert(
                (*k).into(),
                serde_json::Number::from_f64(*v).map_or(serde_json::Value::Null, Into::into),
            );
        }
        writeln!(self.jsonl, "{}", serde_json::Value::Object(obj))
    }

    /// Flushes both files.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.events.flush()?;
        self.jsonl.flush()
    }
}
