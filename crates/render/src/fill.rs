//! Scanline rasterisation of polygons and thick polylines into row-major grids, sampling at pixel
//! centres: a pixel is covered when its centre lies inside the shape (even-odd rule).

/// A row-major grid of `height × width` cells.
#[derive(Debug)]
pub struct Canvas<'a, T> {
    /// Cells, row-major.
    pub cells: &'a mut [T],
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
}

impl<T> Canvas<'_, T> {
    /// Calls `f(row, col, x, y)` for every covered pixel of a polygon given in pixel coordinates
    /// (x = column, y = row, pixel (r, c) centred at (c + 0.5, r + 0.5)).
    pub fn fill_polygon_with(&mut self, poly: &[[f64; 2]], mut f: impl FnMut(&mut T, usize, usize)) {
        if poly.len() < 3 || poly.iter().any(|p| !(p[0].is_finite() && p[1].is_finite())) {
            return;
        }
        let (mut min_y, mut max_y) = (f64::INFINITY, f64::NEG_INFINITY);
        for p in poly {
            min_y = min_y.min(p[1]);
            max_y = max_y.max(p[1]);
        }
        let r0 = ((min_y - 0.5).ceil().max(0.0)) as usize;
        let r1 = (max_y - 0.5).floor();
        if r1 < 0.0 || !r1.is_finite() {
            return;
        }
        let r1 = (r1 as usize).min(self.height.saturating_sub(1));
        let mut xs: Vec<f64> = Vec::with_capacity(8);
        for r in r0..=r1 {
            let yc = r as f64 + 0.5;
            xs.clear();
            for i in 0..poly.len() {
                let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
                if (a[1] <= yc && yc < b[1]) || (b[1] <= yc && yc < a[1]) {
                    xs.push(a[0] + (yc - a[1]) * (b[0] - a[0]) / (b[1] - a[1]));
                }
            }
            xs.sort_by(f64::total_cmp);
            for pair in xs.chunks_exact(2) {
                let c0 = (pair[0] - 0.5).ceil().max(0.0) as usize;
                let c1 = ((pair[1] - 0.5).ceil().min(self.width as f64)).max(0.0) as usize;
                for c in c0..c1 {
                    f(&mut self.cells[r * self.width + c], r, c);
                }
            }
        }
    }

    /// Calls `f` for every pixel covered by a polyline of width `width` (pixels), drawn as one rectangle
    /// per segment with square caps so that joints have no gaps.
    pub fn stroke_with(&mut self, line: &[[f64; 2]], width: f64, mut f: impl FnMut(&mut T, usize, usize)) {
        let h = width / 2.0;
        for seg in line.windows(2) {
            let (a, b) = (seg[0], seg[1]);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let len = dx.hypot(dy);
            if len < 1e-9 {
                continue;
            }
            let (ux, uy) = (dx / len * h, dy / len * h);
            let quad = [
                [a[0] - ux - uy, a[1] - uy + ux],
                [b[0] + ux - uy, b[1] + uy + ux],
                [b[0] + ux + uy, b[1] + uy - ux],
                [a[0] - ux + uy, a[1] - uy - ux],
            ];
            self.fill_polygon_with(&quad, &mut f);
        }
    }
}

impl<T: Copy> Canvas<'_, T> {
    /// Sets every pixel covered by a polygon to `value`.
    pub fn fill_polygon(&mut self, poly: &[[f64; 2]], value: T) {
        self.fill_polygon_with(poly, |cell, _, _| *cell = value);
    }

    /// Sets every pixel covered by a thick polyline to `value`.
    pub fn stroke(&mut self, line: &[[f64; 2]], width: f64, value: T) {
        self.stroke_with(line, width, |cell, _, _| *cell = value);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn count(cells: &[u8]) -> usize {
        cells.iter().filter(|&&c| c > 0).count()
    }

    #[test]
    fn axis_aligned_rectangle_covers_exactly_its_pixel_centres() {
        let mut cells = vec![0u8; 10 * 10];
        let mut c = Canvas {
            cells: &mut cells,
            width: 10,
            height: 10,
        };
        c.fill_polygon(&[[2.0, 3.0], [6.0, 3.0], [6.0, 5.0], [2.0, 5.0]], 1);
        // Columns 2..6 (centres 2.5..5.5), rows 3..5 (centres 3.5, 4.5).
        assert_eq!(count(&cells), 8);
        for r in 3..5 {
            for col in 2..6 {
                assert_eq!(cells[r * 10 + col], 1);
            }
        }
    }

    #[test]
    fn clipping_and_degenerate_inputs_are_safe() {
        let mut cells = vec![0u8; 4 * 4];
        let mut c = Canvas {
            cells: &mut cells,
            width: 4,
            height: 4,
        };
        c.fill_polygon(
            &[[-10.0, -10.0], [100.0, -10.0], [100.0, 100.0], [-10.0, 100.0]],
            1,
        );
        c.fill_polygon(&[[1.0, 1.0], [2.0, 2.0]], 2);
        c.fill_polygon(&[[f64::NAN, 0.0], [1.0, 1.0], [0.0, 1.0]], 3);
        c.stroke(&[[1.0, 1.0], [1.0, 1.0]], 2.0, 4);
        assert_eq!(count(&cells), 16);
        assert!(cells.iter().all(|&v| v == 1));
    }

    #[test]
    fn triangle_area_matches_pixel_count() {
        let mut cells = vec![0u8; 200 * 200];
        let mut c = Canvas {
            cells: &mut cells,
            width: 200,
            height: 200,
        };
        c.fill_polygon(&[[10.0, 10.0], [190.0, 30.0], [60.0, 180.0]], 1);
        let area = 0.5 * ((190.0 - 10.0) * (180.0 - 10.0) - (60.0 - 10.0) * (30.0 - 10.0_f64)).abs();
        let n = count(&cells) as f64;
        assert!((n - area).abs() / area < 0.01, "{n} vs {area}");
    }

    #[test]
    fn one_pixel_diagonal_strokes_have_no_gaps() {
        let mut cells = vec![0u8; 50 * 50];
        let mut c = Canvas {
            cells: &mut cells,
            width: 50,
            height: 50,
        };
        c.stroke(&[[5.0, 5.0], [45.0, 40.0]], 1.0, 1);
        // Every row the line passes through has a covered pixel.
        for r in 6..39 {
            assert!((0..50).any(|col| cells[r * 50 + col] == 1), "gap at row {r}");
        }
    }
}
