//! A small element stream over quick-xml that keeps byte offsets, so that errors can name file and line.

use crate::error::{DataError, Result, io};
use quick_xml::events::{BytesStart, Event};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// One opening (or self-closing) element with its attributes.
#[derive(Debug, Clone)]
pub struct Element {
    /// Tag name.
    pub name: String,
    attrs: Vec<(String, String)>,
    /// Byte offset of the element, for error lines.
    pub offset: u64,
}

/// What the stream yields.
#[derive(Debug)]
pub enum Item {
    /// `<name …>` or `<name …/>`; a self-closing element is followed by its own `Close`.
    Open(Element),
    /// `</name>`.
    Close(String),
}

/// Elements of an XML file, in document order.
pub struct XmlStream<R: BufRead> {
    reader: quick_xml::Reader<R>,
    buf: Vec<u8>,
    path: PathBuf,
    pending_close: Option<String>,
}

impl XmlStream<BufReader<std::fs::File>> {
    /// Opens a file.
    pub fn open(path: &Path) -> Result<Self> {
        let f = std::fs::File::open(path).map_err(io(path))?;
        Ok(Self::new(BufReader::with_capacity(1 << 16, f), path))
    }
}

impl<R: BufRead> XmlStream<R> {
    /// A stream over `reader`; `path` names it in errors.
    pub fn new(reader: R, path: &Path) -> Self {
        let mut reader = quick_xml::Reader::from_reader(reader);
        reader.config_mut().trim_text(true);
        Self {
            reader,
            buf: Vec::new(),
            path: path.into(),
            pending_close: None,
        }
    }

    /// The next element event, or `None` at the end of the document.
    pub fn next(&mut self) -> Result<Option<Item>> {
        if let Some(name) = self.pending_close.take() {
            return Ok(Some(Item::Close(name)));
        }
        loop {
            self.buf.clear();
            let event = self.reader.read_event_into(&mut self.buf).map_err(|e| {
                let at = self.reader.error_position();
                input_error(&self.path, at, format!("malformed XML: {e}"))
            })?;
            // The element starts where its text (`<`, content, `/`?, `>`) ends minus its length; the position
            // before reading can sit on an earlier line, ahead of skipped whitespace.
            let end = self.reader.buffer_position();
            match event {
                Event::Start(e) => {
                    let offset = end.saturating_sub(e.as_ref().len() as u64 + 2);
                    return Ok(Some(Item::Open(element(&self.path, &e, offset)?)));
                }
                Event::Empty(e) => {
                    let offset = end.saturating_sub(e.as_ref().len() as u64 + 3);
                    let el = element(&self.path, &e, offset)?;
                    self.pending_close = Some(el.name.clone());
                    return Ok(Some(Item::Open(el)));
                }
                Event::End(e) => {
                    return Ok(Some(Item::Close(
                        String::from_utf8_lossy(e.name().as_ref()).into_owned(),
                    )));
                }
                Event::Eof => return Ok(None),
                _ => {}
            }
        }
    }

    /// An input error at `el`'s line.
    pub fn error(&self, el: &Element, message: impl Into<String>) -> DataError {
        input_error(&self.path, el.offset, message.into())
    }
}

fn element(path: &Path, e: &BytesStart<'_>, offset: u64) -> Result<Element> {
    let name = String::from_utf8_lossy(e.name().as_ref()).into_owned();
    let mut attrs = Vec::new();
    for a in e.attributes() {
        let a = a.map_err(|err| input_error(path, offset, format!("<{name}>: bad attribute: {err}")))?;
        let key = String::from_utf8_lossy(a.key.as_ref()).into_owned();
        let value = a
            .unescape_value()
            .map_err(|err| input_error(path, offset, format!("<{name}> {key}: {err}")))?
            .into_owned();
        attrs.push((key, value));
    }
    Ok(Element { name, attrs, offset })
}

impl Element {
    /// An attribute, if present.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.attrs.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str())
    }

    /// A required attribute.
    pub fn req<R: BufRead>(&self, key: &str, s: &XmlStream<R>) -> Result<&str> {
        self.get(key)
            .ok_or_else(|| s.error(self, format!("<{}> lacks the `{key}` attribute", self.name)))
    }

    /// A required finite number.
    pub fn num<R: BufRead>(&self, key: &str, s: &XmlStream<R>) -> Result<f64> {
        let v = self.req(key, s)?;
        v.parse::<f64>().ok().filter(|x| x.is_finite()).ok_or_else(|| {
            s.error(
                self,
                format!("<{}> {key}=\"{v}\" is not a finite number", self.name),
            )
        })
    }

    /// An optional finite number.
    pub fn opt_num<R: BufRead>(&self, key: &str, s: &XmlStream<R>) -> Result<Option<f64>> {
        match self.get(key) {
            None => Ok(None),
            Some(_) => self.num(key, s).map(Some),
        }
    }

    /// A SUMO shape (`x,y x,y …`) as points.
    pub fn shape<R: BufRead>(&self, key: &str, s: &XmlStream<R>) -> Result<Vec<[f64; 2]>> {
        let text = self.req(key, s)?;
        text.split_whitespace()
            .map(|pair| {
                let mut it = pair
                    .split(',')
                    .map(|v| v.parse::<f64>().ok().filter(|x| x.is_finite()));
                match (it.next().flatten(), it.next().flatten()) {
                    (Some(x), Some(y)) => Ok([x, y]),
                    _ => Err(s.error(
                        self,
                        format!("<{}> {key}: `{pair}` is not an `x,y` pair", self.name),
                    )),
                }
            })
            .collect()
    }
}

/// An input error at byte `offset` of `path`; the line is counted from the file.
pub fn input_error(path: &Path, offset: u64, message: String) -> DataError {
    DataError::Input {
        path: path.into(),
        line: line_at(path, offset),
        message,
    }
}

/// 1-based line of a byte offset (best effort: 0 when the file cannot be read again).
fn line_at(path: &Path, offset: u64) -> usize {
    let Ok(f) = std::fs::File::open(path) else {
        return 0;
    };
    let mut r = BufReader::new(f).take(offset);
    let mut buf = [0u8; 1 << 16];
    let mut lines = 1;
    while let Ok(n) = r.read(&mut buf) {
        if n == 0 {
            break;
        }
        lines += buf[..n].iter().filter(|&&b| b == b'\n').count();
    }
    lines
}
