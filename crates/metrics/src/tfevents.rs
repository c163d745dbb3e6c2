//! TensorBoard event files: TFRecord framing (length, masked CRC32C) around `Event` protocol buffers.
//!
//! Only what scalar logging needs is encoded: the version event and `Event{wall_time, step,
//! summary{value{tag, simple_value}}}`. Field numbers follow TensorFlow's `event.proto` and `summary.proto`.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// CRC32C (Castagnoli), bitwise table.
fn crc32c(data: &[u8]) -> u32 {
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let mut c = i as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0x82F6_3B78 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
            *e = c;
        }
        t
    });
    !data.iter().fold(!0u32, |c, &b| {
        table[((c ^ u32::from(b)) & 0xff) as usize] ^ (c >> 8)
    })
}

/// TFRecord's masked CRC.
fn masked(data: &[u8]) -> u32 {
    let c = crc32c(data);
    (c.rotate_right(15)).wrapping_add(0xa282_ead8)
}

fn varint(mut v: u64, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn key(field: u64, wire: u64, out: &mut Vec<u8>) {
    varint((field << 3) | wire, out);
}

fn bytes_field(field: u64, data: &[u8], out: &mut Vec<u8>) {
    key(field, 2, out);
    varint(data.len() as u64, out);
    out.extend_from_slice(data);
}

/// `Event{wall_time, step}` followed by `extra` (already-encoded fields).
fn event(wall_time: f64, step: i64, extra: &[u8]) -> Vec<u8> {
    let mut e = Vec::with_capacity(32 + extra.len());
    key(1, 1, &mut e);
    e.extend_from_slice(&wall_time.to_le_bytes());
    key(2, 0, &mut e);
    varint(step as u64, &mut e);
    e.extend_from_slice(extra);
    e
}

/// Writes scalars to `events.out.tfevents.<time>.<host>` in a log directory.
#[derive(Debug)]
pub struct EventWriter {
    path: PathBuf,
    out: BufWriter<File>,
}

impl EventWriter {
    /// Creates the directory and a new event file in it.
    pub fn create(dir: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let now = wall_time();
        let host = std::env::var("HOSTNAME").unwrap_or_else(|_| "umgen".into());
        let path = dir.join(format!("events.out.tfevents.{}.{host}", now as u64));
        let mut w = Self {
            out: BufWriter::new(File::create(&path)?),
            path,
        };
        let mut version = Vec::new();
        bytes_field(3, b"brain.Event:2", &mut version);
        w.record(&event(now, 0, &version))?;
        w.out.flush()?;
        Ok(w)
    }

    /// The event file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends scalars at `step`.
    pub fn scalars(&mut self, step: u64, values: &[(&str, f64)]) -> std::io::Result<()> {
        let mut summary = Vec::new();
        for (tag, v) in values {
            let mut value = Vec::new();
            bytes_field(1, tag.as_bytes(), &mut value);
            key(2, 5, &mut value);
            value.extend_from_slice(&(*v as f32).to_le_bytes());
            bytes_field(1, &value, &mut summary);
        }
        let mut extra = Vec::new();
        bytes_field(5, &summary, &mut extra);
        self.record(&event(wall_time(), step as i64, &extra))
    }

    /// Flushes buffered events to the file.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }

    fn record(&mut self, data: &[u8]) -> std::io::Result<()> {
        let len = (data.len() as u64).to_le_bytes();
        self.out.write_all(&len)?;
        self.out.write_all(&masked(&len).to_le_bytes())?;
        self.out.write_all(data)?;
        self.out.write_all(&masked(data).to_le_bytes())
    }
}

fn wall_time() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Reads back the scalars of an event file, `(step, tag, value)`, checking every CRC. For tests and
/// `umgen` commands that summarise runs.
pub fn read_scalars(path: &Path) -> std::io::Result<Vec<(u64, String, f32)>> {
    let bytes = std::fs::read(path)?;
    let bad = |m: &str| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{}: {m}", path.display()),
        )
    };
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let len_bytes = bytes
            .get(i..i + 8)
            .ok_or_else(|| bad("truncated record length"))?;
        let crc = bytes.get(i + 8..i + 12).ok_or_else(|| bad("truncated record"))?;
        if masked(len_bytes).to_le_bytes() != crc {
            return Err(bad("length checksum mismatch"));
        }
        let n = u64::from_le_bytes(len_bytes.try_into().map_err(|_| bad("length"))?) as usize;
        let data = bytes
            .get(i + 12..i + 12 + n)
            .ok_or_else(|| bad("truncated record data"))?;
        let dcrc = bytes
            .get(i + 12 + n..i + 16 + n)
            .ok_or_else(|| bad("truncated record checksum"))?;
        if masked(data).to_le_bytes() != dcrc {
            return Err(bad("data checksum mismatch"));
        }
        decode_event(data, &mut out).ok_or_else(|| bad("malformed event"))?;
        i += 16 + n;
    }
    Ok(out)
}

fn read_varint(d: &[u8], i: &mut usize) -> Option<u64> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let b = *d.get(*i)?;
        *i += 1;
        v |= u64::from(b & 0x7f) << shift;
        if b < 0x80 {
            return Some(v);
        }
    }
    None
}

/// Visits `(field, wire, payload)` of a protobuf message; varints and fixed fields come as their bytes.
fn fields(d: &[u8], mut f: impl FnMut(u64, &[u8], u64)) -> Option<()> {
    let mut i = 0;
    while i < d.len() {
        let k = read_varint(d, &mut i)?;
        let (field, wire) = (k >> 3, k & 7);
        match wire {
            0 => {
                let v = read_varint(d, &mut i)?;
                f(field, &[], v);
            }
            1 => {
                f(field, d.get(i..i + 8)?, 0);
                i += 8;
            }
            2 => {
                let n = read_varint(d, &mut i)? as usize;
                f(field, d.get(i..i + n)?, 0);
                i += n;
            }
            5 => {
                f(field, d.get(i..i + 4)?, 0);
                i += 4;
            }
            _ => return None,
        }
    }
    Some(())
}

fn decode_event(d: &[u8], out: &mut Vec<(u64, String, f32)>) -> Option<()> {
    let (mut step, mut summary) = (0u64, None);
    fields(d, |field, payload, v| match field {
        2 => step = v,
        5 => summary = Some(payload.to_vec()),
        _ => {}
    })?;
    let Some(summary) = summary else { return Some(()) };
    let mut values = Vec::new();
    fields(&summary, |field, payload, _| {
        if field == 1 {
            values.push(payload.to_vec());
        }
    })?;
    for v in values {
        let (mut tag, mut val) = (String::new(), 0f32);
        fields(&v, |field, payload, _| match field {
            1 => tag = String::from_utf8_lossy(payload).into_owned(),
            2 if payload.len() == 4 => {
                val = f32::from_le_bytes([payload[0], payload[1], payload[2], payload[3]])
            }
            _ => {}
        })?;
        out.push((step, tag, val));
    }
    Some(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_matches_the_standard_check_value() {
        // RFC 3720 B.4: CRC32C("123456789") = 0xE3069283; 32 zero bytes = 0x8A9136AA.
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(crc32c(&[0u8; 32]), 0x8A91_36AA);
    }

    #[test]
    fn scalars_round_trip_and_damage_is_detected() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = EventWriter::create(dir.path()).unwrap();
        w.scalars(1, &[("loss/total", 2.5), ("lr", 1e-4)]).unwrap();
        w.scalars(300, &[("loss/total", 1.25)]).unwrap();
        w.flush().unwrap();
        let path = w.path().to_path_buf();
        assert!(
            path.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with("events.out.tfevents.")
        );
        let got = read_scalars(&path).unwrap();
        assert_eq!(
            got,
            vec![
                (1, "loss/total".into(), 2.5),
                (1, "lr".into(), 1e-4),
                (300, "loss/total".into(), 1.25)
            ]
        );
        let mut bytes = std::fs::read(&path).unwrap();
        let n = bytes.len();
        bytes[n - 6] ^= 1;
        std::fs::write(&path, bytes).unwrap();
        assert!(read_scalars(&path).unwrap_err().to_string().contains("checksum"));
    }
}
