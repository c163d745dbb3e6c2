//! Rendered views of a frame: the BEV map raster and the front camera image.

use crate::error::{Result, SceneError};
use serde::{Deserialize, Serialize};

/// A channel-major (C×H×W) map raster; each value is the coverage of a cell by the channel (0 = none,
/// 255 = full), so binary rasters hold 0 and 255.
///
/// The default map is 6×256×256 over 128 m × 128 m around the ego (0.5 m per pixel), row 0 at the front
/// (+x) and column 0 at the left (+y).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapRaster {
    /// Number of channels.
    pub channels: usize,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `channels * height * width` values, channel-major.
    pub data: Vec<u8>,
}

impl MapRaster {
    /// An all-zero raster.
    pub fn zeros(channels: usize, height: usize, width: usize) -> Self {
        Self {
            channels,
            height,
            width,
            data: vec![0; channels * height * width],
        }
    }

    /// A raster from a buffer, checking its size.
    pub fn from_vec(channels: usize, height: usize, width: usize, data: Vec<u8>) -> Result<Self> {
        check_len("map raster", &[channels, height, width], data.len())?;
        Ok(Self {
            channels,
            height,
            width,
            data,
        })
    }

    /// Value at (channel, row, col); `None` outside the raster.
    pub fn get(&self, c: usize, r: usize, col: usize) -> Option<u8> {
        if c < self.channels && r < self.height && col < self.width {
            self.data.get((c * self.height + r) * self.width + col).copied()
        } else {
            None
        }
    }

    /// One channel as a slice of `height * width` values.
    pub fn channel(&self, c: usize) -> Option<&[u8]> {
        let n = self.height * self.width;
        self.data.get(c * n..(c + 1) * n)
    }

    /// One channel, mutable.
    pub fn channel_mut(&mut self, c: usize) -> Option<&mut [u8]> {
        let n = self.height * self.width;
        self.data.get_mut(c * n..(c + 1) * n)
    }
}

/// An RGB camera image, channel-major (3×H×W), u8. The default is 3×256×512.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraImage {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `3 * height * width` values: all red, then all green, then all blue.
    pub data: Vec<u8>,
}

impl CameraImage {
    /// A black image.
    pub fn black(height: usize, width: usize) -> Self {
        Self {
            height,
            width,
            data: vec![0; 3 * height * width],
        }
    }

    /// An image from a channel-major buffer, checking its size.
    pub fn from_vec(height: usize, width: usize, data: Vec<u8>) -> Result<Self> {
        check_len("camera image", &[3, height, width], data.len())?;
        Ok(Self { height, width, data })
    }

    /// RGB at (row, col); `None` outside the image.
    pub fn pixel(&self, r: usize, c: usize) -> Option<[u8; 3]> {
        if r >= self.height || c >= self.width {
            return None;
        }
        let n = self.height * self.width;
        let i = r * self.width + c;
        Some([self.data[i], self.data[n + i], self.data[2 * n + i]])
    }

    /// Sets RGB at (row, col); ignored outside the image.
    pub fn set_pixel(&mut self, r: usize, c: usize, rgb: [u8; 3]) {
        if r >= self.height || c >= self.width {
            return;
        }
        let n = self.height * self.width;
        let i = r * self.width + c;
        for (k, v) in rgb.into_iter().enumerate() {
            self.data[k * n + i] = v;
        }
    }
}

fn check_len(what: &'static str, shape: &[usize], actual: usize) -> Result<()> {
    let expected = shape.iter().product();
    if expected == actual {
        Ok(())
    } else {
        Err(SceneError::BufferSize {
            what,
            shape: shape.to_vec(),
            expected,
            actual,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raster_indexing_is_channel_major() {
        let mut m = MapRaster::zeros(2, 3, 4);
        m.channel_mut(1).unwrap()[2 * 4 + 3] = 7;
        assert_eq!(m.get(1, 2, 3), Some(7));
        assert_eq!(m.data[12 + 11], 7);
        assert_eq!(m.get(2, 0, 0), None);
        assert!(MapRaster::from_vec(2, 3, 4, vec![0; 23]).is_err());
    }

    #[test]
    fn image_pixels_round_trip() {
        let mut im = CameraImage::black(2, 3);
        im.set_pixel(1, 2, [10, 20, 30]);
        assert_eq!(im.pixel(1, 2), Some([10, 20, 30]));
        assert_eq!(im.data[5], 10);
        assert_eq!(im.data[6 + 5], 20);
        assert_eq!(im.pixel(2, 0), None);
        let err = CameraImage::from_vec(2, 3, vec![0; 17]).unwrap_err().to_string();
        assert!(err.contains("camera image") && err.contains("18"), "{err}");
    }
}
