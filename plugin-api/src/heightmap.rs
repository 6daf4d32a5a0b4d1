//! Height maps (issue 25): a probed grid of surface heights that a backend adds to a program's
//! Z, so a cut follows uneven stock (PCB milling, engraving). The host sends one with
//! `load_program` ([`crate::contract::Request::LoadProgram`]`.height_map`), already expressed
//! in the work coordinates the program runs in; a backend that streams points applies it once
//! here, the same way for every backend:
//!
//! * [`HeightMap::correction`]: bilinear interpolation between the four grid points around
//!   (x, y); outside the grid's area the nearest edge's value (X and Y clamped into the area).
//! * [`HeightMap::split`]: where a straight move crosses a grid line, so the corrected path
//!   follows the map cell by cell instead of cutting straight between two far corrected ends.
//!   A move is cut into at most `nx + ny + 1` pieces (it crosses each of the `nx + ny` grid
//!   lines at most once).
//! * [`HeightMap::corrected_path`]: both together, for one move.
//!
//! Sizes are bounded ([`MAX_POINTS_PER_AXIS`]), and [`HeightMap::validate`] refuses anything
//! else before a backend uses a map.

use serde::{Deserialize, Serialize};

/// Most grid points along X or along Y (so at most 2,500 points, 20 KB of heights on the wire).
pub const MAX_POINTS_PER_AXIS: u32 = 50;

/// Largest correction a map may hold, mm (in size; a surface further than this from the work
/// zero is a mistake, not stock).
pub const MAX_CORRECTION_MM: f64 = 1000.0;

/// Slack when deciding whether a point lies on a grid line or inside the area, mm.
const EPS: f64 = 1e-9;

/// A grid of Z corrections over a rectangle of program X/Y: point (i, j) is at
/// `(x0 + i*dx, y0 + j*dy)` and holds `z[j*nx + i]` (row by row, Y from `y0` up).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeightMap {
    /// Program X and Y of the first grid point, mm.
    pub x0: f64,
    pub y0: f64,
    /// Spacing of the columns (X) and rows (Y), mm (> 0).
    pub dx: f64,
    pub dy: f64,
    /// Points along X and along Y (2..=[`MAX_POINTS_PER_AXIS`]).
    pub nx: u32,
    pub ny: u32,
    /// The correction at each point, mm, added to a program's Z there.
    pub z: Vec<f64>,
}

impl HeightMap {
    /// Refuses a map that is not a whole, bounded grid of finite numbers, naming the problem.
    pub fn validate(&self) -> Result<(), String> {
        for (name, n) in [("nx", self.nx), ("ny", self.ny)] {
            if !(2..=MAX_POINTS_PER_AXIS).contains(&n) {
                return Err(format!(
                    "height_map.{name} = {n}: a grid has 2 to {MAX_POINTS_PER_AXIS} points per axis"
                ));
            }
        }
        for (name, v) in [("x0", self.x0), ("y0", self.y0)] {
            if !v.is_finite() {
                return Err(format!(
                    "height_map.{name} must be a finite number, got {v}"
                ));
            }
        }
        for (name, v) in [("dx", self.dx), ("dy", self.dy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!(
                    "height_map.{name} must be a positive spacing in mm, got {v}"
                ));
            }
        }
        let want = self.nx as usize * self.ny as usize;
        if self.z.len() != want {
            return Err(format!(
                "height_map.z has {} values; a {} x {} grid needs {want}",
                self.z.len(),
                self.nx,
                self.ny
            ));
        }
        if let Some((k, v)) = self
            .z
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && v.abs() <= MAX_CORRECTION_MM))
        {
            return Err(format!(
                "height_map.z[{k}] = {v}: a correction is a finite number of at most \
                 {MAX_CORRECTION_MM} mm"
            ));
        }
        Ok(())
    }

    /// The area the grid covers: `[x_min, x_max, y_min, y_max]`.
    pub fn area(&self) -> [f64; 4] {
        [
            self.x0,
            self.x0 + self.dx * f64::from(self.nx - 1),
            self.y0,
            self.y0 + self.dy * f64::from(self.ny - 1),
        ]
    }

    fn at(&self, i: usize, j: usize) -> f64 {
        self.z[j * self.nx as usize + i]
    }

    /// The cell index and the fraction inside it of `v` along an axis of `n` points from `v0`
    /// spaced `d` (clamped into the area).
    fn locate(v: f64, v0: f64, d: f64, n: u32) -> (usize, f64) {
        let cells = (n - 1) as usize;
        let u = ((v - v0) / d).clamp(0.0, cells as f64);
        let i = (u.floor() as usize).min(cells - 1);
        (i, u - i as f64)
    }

    /// The correction at program (x, y), mm: bilinear between the four grid points around it;
    /// outside the area, that of the nearest point of the area.
    pub fn correction(&self, x: f64, y: f64) -> f64 {
        let (i, fx) = Self::locate(x, self.x0, self.dx, self.nx);
        let (j, fy) = Self::locate(y, self.y0, self.dy, self.ny);
        let low = self.at(i, j) * (1.0 - fx) + self.at(i + 1, j) * fx;
        let high = self.at(i, j + 1) * (1.0 - fx) + self.at(i + 1, j + 1) * fx;
        low * (1.0 - fy) + high * fy
    }

    /// Where a straight move from `a` to `b` (program X, Y) crosses a grid line of the area, as
    /// fractions of the move in increasing order, ending with `1.0` (the move's end). A move
    /// that crosses none (or only changes Z) gives `[1.0]`. At most `nx + ny + 1` values.
    pub fn split(&self, a: [f64; 2], b: [f64; 2]) -> Vec<f64> {
        let mut ts = Vec::new();
        for (axis, v0, d, n) in [
            (0, self.x0, self.dx, self.nx),
            (1, self.y0, self.dy, self.ny),
        ] {
            let span = b[axis] - a[axis];
            if span.abs() <= EPS {
                continue;
            }
            for k in 0..n {
                let line = v0 + d * f64::from(k);
                let t = (line - a[axis]) / span;
                if t > EPS && t < 1.0 - EPS {
                    ts.push(t);
                }
            }
        }
        ts.sort_by(f64::total_cmp);
        ts.dedup_by(|later, earlier| (*later - *earlier).abs() <= EPS);
        ts.push(1.0);
        ts
    }

    /// The corrected path of a straight move from `a` to `b` (program X, Y, Z, uncorrected):
    /// the end of each piece [`HeightMap::split`] cuts it into, with the correction there
    /// added to Z. The last point is `b` corrected. Each piece also carries its fraction of
    /// the move (to interpolate what else moves along, e.g. a rotary axis).
    pub fn corrected_path(&self, a: [f64; 3], b: [f64; 3]) -> Vec<(f64, [f64; 3])> {
        self.split([a[0], a[1]], [b[0], b[1]])
            .into_iter()
            .map(|t| {
                let p: [f64; 3] = std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t);
                let p = if t == 1.0 { b } else { p };
                (t, [p[0], p[1], p[2] + self.correction(p[0], p[1])])
            })
            .collect()
    }

    /// Program (x, y, z) as the machine is at it, corrected: the uncorrected point a path
    /// continues from (the inverse of the correction, which depends on X and Y only).
    pub fn uncorrected(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0], p[1], p[2] - self.correction(p[0], p[1])]
    }

    /// The lowest and highest correction over the rectangle `[x_min, x_max, y_min, y_max]`
    /// (exact: a bilinear surface takes its extremes at the corners of the pieces the grid
    /// lines cut the rectangle into).
    pub fn range_over(&self, rect: [f64; 4]) -> (f64, f64) {
        let [x_min, x_max, y_min, y_max] = rect;
        let ticks = |lo: f64, hi: f64, v0: f64, d: f64, n: u32| {
            let mut v = vec![lo, hi];
            v.extend(
                (0..n)
                    .map(|k| v0 + d * f64::from(k))
                    .filter(|&g| g > lo && g < hi),
            );
            v
        };
        let xs = ticks(x_min, x_max, self.x0, self.dx, self.nx);
        let ys = ticks(y_min, y_max, self.y0, self.dy, self.ny);
        let mut range = (f64::INFINITY, f64::NEG_INFINITY);
        for &x in &xs {
            for &y in &ys {
                let c = self.correction(x, y);
                range = (range.0.min(c), range.1.max(c));
            }
        }
        range
    }

    /// The map moved into another frame: X, Y and Z of every point shifted by `shift` (mm).
    pub fn shifted(&self, shift: [f64; 3]) -> HeightMap {
        HeightMap {
            x0: self.x0 + shift[0],
            y0: self.y0 + shift[1],
            z: self.z.iter().map(|z| z + shift[2]).collect(),
            ..self.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A 3 x 3 map over X 0..20, Y 0..10 of the surface z = 0.1 + 0.01 x - 0.02 y + 0.001 x y
    /// (a bilinear surface, which bilinear interpolation reproduces exactly).
    fn saddle() -> HeightMap {
        let f = |x: f64, y: f64| 0.1 + 0.01 * x - 0.02 * y + 0.001 * x * y;
        let mut z = Vec::new();
        for j in 0..3 {
            for i in 0..3 {
                z.push(f(10.0 * f64::from(i), 5.0 * f64::from(j)));
            }
        }
        HeightMap {
            x0: 0.0,
            y0: 0.0,
            dx: 10.0,
            dy: 5.0,
            nx: 3,
            ny: 3,
            z,
        }
    }

    #[test]
    fn interpolation_hits_the_grid_points_and_is_bilinear_between() {
        let m = saddle();
        let f = |x: f64, y: f64| 0.1 + 0.01 * x - 0.02 * y + 0.001 * x * y;
        for (x, y) in [
            (0.0, 0.0),
            (10.0, 5.0),
            (20.0, 10.0),
            (3.0, 7.5),
            (12.5, 1.25),
            (19.99, 9.99),
        ] {
            assert!(
                (m.correction(x, y) - f(x, y)).abs() < 1e-12,
                "{x} {y}: {} vs {}",
                m.correction(x, y),
                f(x, y)
            );
        }
        // A cell of four different heights: the centre is their mean.
        let m = HeightMap {
            x0: 1.0,
            y0: 2.0,
            dx: 2.0,
            dy: 4.0,
            nx: 2,
            ny: 2,
            z: vec![0.0, 1.0, 2.0, 7.0],
        };
        assert!((m.correction(2.0, 4.0) - 2.5).abs() < 1e-12);
        assert!((m.correction(3.0, 2.0) - 1.0).abs() < 1e-12);
        assert!((m.correction(1.0, 6.0) - 2.0).abs() < 1e-12);
        // Outside: the nearest edge (clamped), never extrapolated.
        assert_eq!(m.correction(-50.0, -50.0), 0.0);
        assert_eq!(m.correction(50.0, 50.0), 7.0);
        assert!((m.correction(2.0, -9.0) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn a_move_is_split_where_it_crosses_grid_lines() {
        let m = saddle();
        // Along X over the whole map: crosses x = 10 once (0 and 20 are its ends).
        assert_eq!(m.split([0.0, 1.0], [20.0, 1.0]), vec![0.5, 1.0]);
        // Diagonally: x = 10 at t 0.5, y = 5 at t 0.5 too (one split), then the end.
        assert_eq!(m.split([0.0, 0.0], [20.0, 10.0]), vec![0.5, 1.0]);
        // From outside across the whole area: the area's edges count as grid lines.
        let ts = m.split([-10.0, 2.0], [30.0, 2.0]);
        assert_eq!(ts, vec![0.25, 0.5, 0.75, 1.0]);
        // Backwards works the same way; a plunge is not split.
        assert_eq!(m.split([20.0, 1.0], [0.0, 1.0]), vec![0.5, 1.0]);
        assert_eq!(m.split([3.0, 3.0], [3.0, 3.0]), vec![1.0]);
        // Never more than nx + ny + 1 pieces, on the biggest grid too.
        let big = HeightMap {
            x0: 0.0,
            y0: 0.0,
            dx: 1.0,
            dy: 1.0,
            nx: MAX_POINTS_PER_AXIS,
            ny: MAX_POINTS_PER_AXIS,
            z: vec![0.0; (MAX_POINTS_PER_AXIS * MAX_POINTS_PER_AXIS) as usize],
        };
        assert!(big.validate().is_ok());
        let n = big.split([-1.0, -0.5], [60.0, 61.3]).len();
        assert_eq!(
            n,
            2 * MAX_POINTS_PER_AXIS as usize + 1,
            "every line crossed once"
        );
    }

    #[test]
    fn the_corrected_path_follows_the_map_at_every_piece_end() {
        let m = saddle();
        let path = m.corrected_path([-5.0, 1.0, -0.2], [25.0, 9.0, -0.1]);
        // Every piece ends on a grid line (or at the end), with its own correction added.
        // x = 0, 10, 20 at t = 1/6, 1/2, 5/6 (y = 5 also at 1/2), then the end.
        assert_eq!(path.len(), 4, "{path:?}");
        for (t, p) in &path {
            let z = -0.2 + 0.1 * t;
            assert!((p[2] - (z + m.correction(p[0], p[1]))).abs() < 1e-12);
        }
        let (t, last) = path.last().copied().unwrap();
        assert_eq!(t, 1.0);
        assert!((last[2] - (-0.1 + m.correction(25.0, 9.0))).abs() < 1e-12);
        // The inverse gives back the program point.
        let back = m.uncorrected(last);
        assert!((back[2] + 0.1).abs() < 1e-12);
    }

    #[test]
    fn the_range_over_an_area_is_exact_and_shifting_moves_the_frame() {
        let m = HeightMap {
            x0: 0.0,
            y0: 0.0,
            dx: 10.0,
            dy: 10.0,
            nx: 3,
            ny: 2,
            z: vec![0.0, 1.0, 0.0, -1.0, 0.5, 2.0],
        };
        assert_eq!(m.range_over(m.area()), (-1.0, 2.0));
        // Inside the first column of cells only: 1.0 is at x = 10 (an edge of the area asked).
        assert_eq!(m.range_over([0.0, 10.0, 0.0, 10.0]), (-1.0, 1.0));
        // A small area inside one cell: its corners.
        let (lo, hi) = m.range_over([2.0, 3.0, 0.0, 0.0]);
        assert!(
            (lo - 0.2).abs() < 1e-12 && (hi - 0.3).abs() < 1e-12,
            "{lo} {hi}"
        );
        let s = m.shifted([5.0, -5.0, 0.25]);
        assert_eq!(s.area(), [5.0, 25.0, -5.0, 5.0]);
        assert!((s.correction(15.0, -5.0) - 1.25).abs() < 1e-12);
    }

    #[test]
    fn validation_names_what_is_wrong() {
        let ok = saddle();
        assert!(ok.validate().is_ok());
        for (m, needle) in [
            (
                HeightMap {
                    nx: 1,
                    ..ok.clone()
                },
                "height_map.nx",
            ),
            (
                HeightMap {
                    ny: 51,
                    ..ok.clone()
                },
                "height_map.ny",
            ),
            (
                HeightMap {
                    dx: 0.0,
                    ..ok.clone()
                },
                "height_map.dx",
            ),
            (
                HeightMap {
                    y0: f64::NAN,
                    ..ok.clone()
                },
                "height_map.y0",
            ),
            (
                HeightMap {
                    z: vec![0.0; 8],
                    ..ok.clone()
                },
                "has 8 values",
            ),
            (
                HeightMap {
                    z: [vec![0.0; 8], vec![f64::INFINITY]].concat(),
                    ..ok.clone()
                },
                "height_map.z[8]",
            ),
        ] {
            let e = m.validate().unwrap_err();
            assert!(e.contains(needle), "{needle}: {e}");
        }
        // The wire shape.
        let v = serde_json::to_value(&ok).unwrap();
        assert_eq!(v["nx"], 3);
        let back: HeightMap = serde_json::from_value(v).unwrap();
        assert_eq!(back, ok);
    }
}
