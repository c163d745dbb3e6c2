//! An RGB image with the few drawing operations the pictures need.

use umgen_render::Canvas;
use umgen_scene::CameraImage;

/// An interleaved RGB image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rgb {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `height × width` pixels, row-major.
    pub pixels: Vec<[u8; 3]>,
}

impl Rgb {
    /// An image filled with one colour.
    pub fn filled(width: usize, height: usize, c: [u8; 3]) -> Self {
        Self {
            width,
            height,
            pixels: vec![c; width * height],
        }
    }

    /// The image enlarged `k` times (nearest neighbour), for small rasters.
    pub fn scaled(&self, k: usize) -> Self {
        let k = k.max(1);
        let (w, h) = (self.width * k, self.height * k);
        let pixels = (0..h)
            .flat_map(|r| (0..w).map(move |c| (r / k) * self.width + c / k))
            .map(|i| self.pixels[i])
            .collect();
        Self {
            width: w,
            height: h,
            pixels,
        }
    }

    /// The pixel at (row, col).
    pub fn get(&self, r: usize, c: usize) -> Option<[u8; 3]> {
        (r < self.height && c < self.width).then(|| self.pixels[r * self.width + c])
    }

    /// A canvas for polygon and line drawing.
    pub fn canvas(&mut self) -> Canvas<'_, [u8; 3]> {
        Canvas {
            cells: &mut self.pixels,
            width: self.width,
            height: self.height,
        }
    }

    /// Draws a line `width` pixels wide.
    pub fn line(&mut self, a: [f64; 2], b: [f64; 2], width: f64, c: [u8; 3]) {
        self.canvas().stroke(&[a, b], width, c);
    }

    /// Draws an arrow from `a` to `b` with a head of `head` pixels.
    pub fn arrow(&mut self, a: [f64; 2], b: [f64; 2], width: f64, head: f64, c: [u8; 3]) {
        self.line(a, b, width, c);
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let n = dx.hypot(dy);
        if n < 1e-6 {
            return;
        }
        let (ux, uy) = (dx / n, dy / n);
        for s in [-1.0, 1.0] {
            let tip = [
                b[0] - head * (ux * 0.87 - s * uy * 0.5),
                b[1] - head * (uy * 0.87 + s * ux * 0.5),
            ];
            self.line(b, tip, width, c);
        }
    }

    /// Copies `src` with its top-left corner at (row, col), clipped to this image.
    pub fn blit(&mut self, src: &Rgb, row: usize, col: usize) {
        for r in 0..src.height.min(self.height.saturating_sub(row)) {
            for c in 0..src.width.min(self.width.saturating_sub(col)) {
                self.pixels[(row + r) * self.width + col + c] = src.pixels[r * src.width + c];
            }
        }
    }

    /// A camera image, scaled by nearest neighbour to `width` columns.
    pub fn from_camera(img: &CameraImage, width: usize) -> Self {
        let height = (img.height * width).div_ceil(img.width.max(1));
        let mut out = Self::filled(width, height, [0, 0, 0]);
        for r in 0..height {
            for c in 0..width {
                let (sr, sc) = (r * img.height / height.max(1), c * img.width / width.max(1));
                if let Some(p) = img.pixel(sr, sc) {
                    out.pixels[r * width + c] = p;
                }
            }
        }
        out
    }

    /// Interleaved bytes (`r, g, b, r, g, b, …`).
    pub fn bytes(&self) -> Vec<u8> {
        self.pixels.iter().flatten().copied().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scaling_repeats_each_pixel_k_by_k() {
        let mut img = Rgb::filled(2, 1, [0, 0, 0]);
        img.pixels[1] = [9, 9, 9];
        let s = img.scaled(3);
        assert_eq!((s.width, s.height), (6, 3));
        assert_eq!(s.get(2, 2), Some([0, 0, 0]));
        assert_eq!(s.get(0, 3), Some([9, 9, 9]));
        assert_eq!(s.get(2, 5), Some([9, 9, 9]));
        assert_eq!(img.scaled(0), img);
    }
}
