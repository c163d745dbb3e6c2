//! A pinhole front camera: the road surface, markings and crosswalks from the map geometry, and agents as
//! shaded 3D boxes coloured by category. Deterministic: the same inputs give the same pixels.

use crate::fill::Canvas;
use crate::palette::{self, Class};
use std::sync::OnceLock;
use umgen_scene::{Agent, CameraImage, Pose2, RoadNetwork, boxes_overlap};

/// The camera's mounting and optics. The camera sits on the ego's centre line `mount_x` metres ahead of
/// the ego origin, `height_m` above the ground, looking forward and pitched down by `pitch_deg`.
#[derive(Debug)]
pub struct Camera {
    /// Rows and columns of the image.
    pub size: [usize; 2],
    /// Horizontal field of view (degrees).
    pub hfov_deg: f64,
    /// Height above the ground (m).
    pub height_m: f64,
    /// Downward pitch (degrees).
    pub pitch_deg: f64,
    /// Forward offset from the ego origin (m).
    pub mount_x: f64,
    /// Ground farther than this fades into the horizon haze (m).
    pub max_distance: f64,
    rays: OnceLock<Vec<[f64; 3]>>,
}

impl Default for Camera {
    /// 256×512, 90° horizontal field of view, 1.6 m high, 3° down, 1 m ahead of the ego origin.
    fn default() -> Self {
        Self::new([256, 512], 90.0, 1.6, 3.0, 1.0, 80.0)
    }
}

/// Ground texture cell size (m) for a 512-pixel-wide image; narrower images use coarser cells, so that a
/// cell stays about as large as a pixel of the near road.
const TEXEL_512: f64 = 0.25;

impl Camera {
    /// A camera; see the field docs.
    pub fn new(
        size: [usize; 2],
        hfov_deg: f64,
        height_m: f64,
        pitch_deg: f64,
        mount_x: f64,
        max_distance: f64,
    ) -> Self {
        Self {
            size,
            hfov_deg,
            height_m,
            pitch_deg,
            mount_x,
            max_distance,
            rays: OnceLock::new(),
        }
    }

    /// Focal length in pixels.
    pub fn focal_px(&self) -> f64 {
        (self.size[1] as f64 / 2.0) / (self.hfov_deg.to_radians() / 2.0).tan()
    }

    /// Camera axes in the ego frame: forward, right, down.
    fn axes(&self) -> [[f64; 3]; 3] {
        let (s, c) = self.pitch_deg.to_radians().sin_cos();
        [[c, 0.0, -s], [0.0, -1.0, 0.0], [-s, 0.0, -c]]
    }

    fn origin(&self) -> [f64; 3] {
        [self.mount_x, 0.0, self.height_m]
    }

    /// Unit ray direction (ego frame) through every pixel centre, row-major.
    fn rays(&self) -> &[[f64; 3]] {
        self.rays.get_or_init(|| {
            let [h, w] = self.size;
            let f = self.focal_px();
            let [fw, rt, dn] = self.axes();
            let mut out = Vec::with_capacity(h * w);
            for r in 0..h {
                for c in 0..w {
                    let u = (c as f64 + 0.5 - w as f64 / 2.0) / f;
                    let v = (r as f64 + 0.5 - h as f64 / 2.0) / f;
                    let d = [0, 1, 2].map(|k| fw[k] + u * rt[k] + v * dn[k]);
                    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    out.push(d.map(|x| x / n));
                }
            }
            out
        })
    }

    /// Projects an ego-frame point to (column, row, depth along the optical axis).
    pub fn project(&self, p: [f64; 3]) -> [f64; 3] {
        let o = self.origin();
        let d = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
        let [fw, rt, dn] = self.axes();
        let dot = |a: [f64; 3]| a[0] * d[0] + a[1] * d[1] + a[2] * d[2];
        let (z, x, y) = (dot(fw), dot(rt), dot(dn));
        let f = self.focal_px();
        [
            self.size[1] as f64 / 2.0 + f * x / z,
            self.size[0] as f64 / 2.0 + f * y / z,
            z,
        ]
    }

    /// Renders the view from `pose` on `network` with `agents` (in the ego frame).
    pub fn render(&self, network: &RoadNetwork, pose: &Pose2, agents: &[Agent]) -> CameraImage {
        let [h, w] = self.size;
        let texel = TEXEL_512 * (512.0 / w.max(1) as f64).max(1.0);
        let tex = GroundTexture::render(network, pose, self.max_distance, texel);
        let rays = self.rays();
        let o = self.origin();
        let mut image = CameraImage::black(h, w);
        let mut depth = vec![f64::INFINITY; h * w];
        for (i, d) in rays.iter().enumerate() {
            let rgb = if d[2] < -1e-6 {
                let t = o[2] / -d[2];
                depth[i] = t;
                let (x, y) = (o[0] + t * d[0], o[1] + t * d[1]);
                let base = tex.class_at(x, y).map_or(palette::FAR_GROUND, |(class, stripe)| {
                    palette::ground(class, stripe)
                });
                palette::fog(base, t / self.max_distance)
            } else {
                palette::sky(d[2])
            };
            image.set_pixel(i / w, i % w, rgb);
        }
        let mut order: Vec<&Agent> = agents.iter().collect();
        order.sort_by(|a, b| b.distance().total_cmp(&a.distance()));
        for agent in order {
            self.draw_box(agent, &mut image, &mut depth);
        }
        image
    }

    fn draw_box(&self, a: &Agent, image: &mut CameraImage, depth: &mut [f64]) {
        let (s, c) = a.heading.sin_cos();
        let corner = |sx: f64, sy: f64, sz: f64| {
            let (lx, ly) = (sx * a.length / 2.0, sy * a.width / 2.0);
            [
                a.x + c * lx - s * ly,
                a.y + s * lx + c * ly,
                a.z + sz * a.height / 2.0,
            ]
        };
        // Faces as (corner signs, outward normal in the ego frame).
        let faces: [([[f64; 3]; 4], [f64; 3]); 6] = [
            (
                [[1., -1., -1.], [1., 1., -1.], [1., 1., 1.], [1., -1., 1.]],
                [c, s, 0.],
            ),
            (
                [[-1., 1., -1.], [-1., -1., -1.], [-1., -1., 1.], [-1., 1., 1.]],
                [-c, -s, 0.],
            ),
            (
                [[1., 1., -1.], [-1., 1., -1.], [-1., 1., 1.], [1., 1., 1.]],
                [-s, c, 0.],
            ),
            (
                [[-1., -1., -1.], [1., -1., -1.], [1., -1., 1.], [-1., -1., 1.]],
                [s, -c, 0.],
            ),
            (
                [[1., -1., 1.], [1., 1., 1.], [-1., 1., 1.], [-1., -1., 1.]],
                [0., 0., 1.],
            ),
            (
                [[1., 1., -1.], [1., -1., -1.], [-1., -1., -1.], [-1., 1., -1.]],
                [0., 0., -1.],
            ),
        ];
        let o = self.origin();
        let rays = self.rays();
        let [rows, cols] = self.size;
        for (signs, n) in faces {
            let pts = signs.map(|[x, y, z]| corner(x, y, z));
            let centre = [0, 1, 2].map(|k| pts.iter().map(|p| p[k]).sum::<f64>() / 4.0);
            let to_face = [centre[0] - o[0], centre[1] - o[1], centre[2] - o[2]];
            let facing = to_face[0] * n[0] + to_face[1] * n[1] + to_face[2] * n[2];
            if facing >= 0.0 {
                continue;
            }
            let Some(poly) = self.clip_and_project(&pts) else {
                continue;
            };
            let rgb = palette::shade(palette::agent(a.category), n);
            let plane_d = pts[0][0] * n[0] + pts[0][1] * n[1] + pts[0][2] * n[2]
                - (o[0] * n[0] + o[1] * n[1] + o[2] * n[2]);
            let data = &mut image.data;
            let plane = rows * cols;
            let mut canvas = Canvas {
                cells: depth,
                width: cols,
                height: rows,
            };
            canvas.fill_polygon_with(&poly, |cell, r, col| {
                let d = rays[r * cols + col];
                let denom = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
                let t = if denom.abs() > 1e-9 {
                    plane_d / denom
                } else {
                    f64::INFINITY
                };
                if t > 0.0 && t < *cell {
                    *cell = t;
                    let i = r * cols + col;
                    data[i] = rgb[0];
                    data[plane + i] = rgb[1];
                    data[2 * plane + i] = rgb[2];
                }
            });
        }
    }

    /// Clips a face against the near plane (depth 0.1 m) and projects it to pixel coordinates.
    fn clip_and_project(&self, pts: &[[f64; 3]; 4]) -> Option<Vec<[f64; 2]>> {
        const NEAR: f64 = 0.1;
        let proj: Vec<[f64; 3]> = pts.iter().map(|&p| self.project(p)).collect();
        let depth = |i: usize| proj[i][2];
        if (0..4).all(|i| depth(i) < NEAR) {
            return None;
        }
        let mut out = Vec::with_capacity(6);
        for i in 0..4 {
            let j = (i + 1) % 4;
            let (a, b) = (pts[i], pts[j]);
            if depth(i) >= NEAR {
                out.push([proj[i][0], proj[i][1]]);
            }
            if (depth(i) >= NEAR) != (depth(j) >= NEAR) {
                let t = (NEAR - depth(i)) / (depth(j) - depth(i));
                let p = [0, 1, 2].map(|k| a[k] + t * (b[k] - a[k]));
                let q = self.project(p);
                out.push([q[0], q[1]]);
            }
        }
        (out.len() >= 3).then_some(out)
    }
}

/// Semantic classes of the ground ahead of the ego, rasterised once per frame and sampled per pixel.
struct GroundTexture {
    texel: f64,
    classes: Vec<Class>,
    crosswalk: Vec<u16>,
    directions: Vec<[f64; 2]>,
    rows: usize,
    cols: usize,
    reach: f64,
    pose: Pose2,
}

impl GroundTexture {
    fn render(net: &RoadNetwork, pose: &Pose2, reach: f64, texel: f64) -> Self {
        let rows = (reach / texel).ceil() as usize;
        let cols = 2 * rows;
        let mut classes = vec![Class::Grass; rows * cols];
        let mut crosswalk = vec![0u16; rows * cols];
        let to_px = |p: &[f64; 2]| {
            let l = pose.to_local(*p);
            [(reach - l[1]) / texel, (reach - l[0]) / texel]
        };
        let centre = pose.to_parent([reach / 2.0, 0.0]);
        let r = reach * 1.2;
        let view = [centre[0] - r, centre[1] - r, centre[0] + r, centre[1] + r];
        let b = net.bounds();
        let mut canvas = Canvas {
            cells: &mut classes,
            width: cols,
            height: rows,
        };
        let mut fill = |items: &[Vec<[f64; 2]>], boxes: &[[f64; 4]], class: Class| {
            for (poly, bb) in items.iter().zip(boxes) {
                if boxes_overlap(bb, &view) {
                    canvas.fill_polygon(&poly.iter().map(to_px).collect::<Vec<_>>(), class);
                }
            }
        };
        fill(&net.sidewalks, &b.sidewalks, Class::Sidewalk);
        fill(&net.intersections, &b.intersections, Class::Road);
        fill(&net.lanes, &b.lanes, Class::Road);
        fill(&net.connectors, &b.connectors, Class::Road);
        let mut directions = Vec::new();
        for (cw, bb) in net.crosswalks.iter().zip(&b.crosswalks) {
            if !boxes_overlap(bb, &view) {
                continue;
            }
            directions.push(cw.direction);
            let id = directions.len() as u16;
            let px: Vec<[f64; 2]> = cw.polygon.iter().map(to_px).collect();
            let mut ids = Canvas {
                cells: &mut crosswalk,
                width: cols,
                height: rows,
            };
            ids.fill_polygon(&px, id);
            canvas.fill_polygon(&px, Class::Crosswalk);
        }
        for (marks, boxes) in [(&net.dividers, &b.dividers), (&net.stop_lines, &b.stop_lines)] {
            for (m, bb) in marks.iter().zip(boxes) {
                if boxes_overlap(bb, &view) {
                    canvas.stroke(
                        &m.line.iter().map(to_px).collect::<Vec<_>>(),
                        (m.width / texel).max(1.0),
                        Class::Marking,
                    );
                }
            }
        }
        Self {
            texel,
            classes,
            crosswalk,
            directions,
            rows,
            cols,
            reach,
            pose: *pose,
        }
    }

    /// Class at an ego-frame ground point and, on crosswalks, whether it lies on a white stripe.
    fn class_at(&self, x: f64, y: f64) -> Option<(Class, bool)> {
        let (r, c) = ((self.reach - x) / self.texel, (self.reach - y) / self.texel);
        if r < 0.0 || c < 0.0 || r >= self.rows as f64 || c >= self.cols as f64 {
            return None;
        }
        let i = r as usize * self.cols + c as usize;
        let class = self.classes[i];
        let stripe = class == Class::Crosswalk
            && self
                .directions
                .get(usize::from(self.crosswalk[i]).wrapping_sub(1))
                .is_some_and(|d| {
                    // Stripes run along the walking direction: alternate across it every 0.5 m.
                    let g = self.pose.to_parent([x, y]);
                    ((g[0] * -d[1] + g[1] * d[0]) / 0.5).floor().rem_euclid(2.0) < 1.0
                });
        Some((class, stripe))
    }
}
