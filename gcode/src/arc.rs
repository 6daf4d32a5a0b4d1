//! Arc geometry (points, bounds, length) and the linearisation adapter.

use crate::{ErrorKind, GcodeError, Motion, Plane, Point};
use std::f64::consts::{FRAC_PI_2, TAU};

/// Length of (x, y). `f64::hypot` guards against overflow near 1e154 at
/// several times the cost, a libm call per arc; coordinates here are far
/// smaller (arc radii are capped by the interpreter).
#[inline]
pub(crate) fn len2(x: f64, y: f64) -> f64 {
    (x * x + y * y).sqrt()
}

/// Smallest tolerance [`linearise`] accepts; smaller (or NaN) values are
/// raised to it so that a bad setting cannot produce an endless stream.
pub const MIN_TOLERANCE_MM: f64 = 1e-6;

/// Geometry of one [`Motion::Arc`], in the plane's (first, second, normal) axes.
/// Angles are counter-clockwise positive from the first to the second axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArcGeometry {
    pub from: Point,
    pub to: Point,
    pub centre: Point,
    /// (first, second, normal) axis indices, see [`Plane::axes`].
    pub axes: (usize, usize, usize),
    /// Start radius and end radius in the plane (equal unless a tolerated mismatch).
    pub r0: f64,
    pub r1: f64,
    /// Signed sweep: positive counter-clockwise (G3), negative clockwise (G2).
    pub sweep: f64,
}

impl ArcGeometry {
    /// Geometry of an arc motion, `None` for anything else.
    pub fn from_motion(m: &Motion) -> Option<Self> {
        match *m {
            Motion::Arc {
                from,
                to,
                centre,
                plane,
                clockwise,
                sweep_rad,
                ..
            } => Some(Self::new(from, to, centre, plane, clockwise, sweep_rad)),
            _ => None,
        }
    }

    pub fn new(
        from: Point,
        to: Point,
        centre: Point,
        plane: Plane,
        clockwise: bool,
        sweep_rad: f64,
    ) -> Self {
        let axes = plane.axes();
        let (a, b, _) = axes;
        let r0 = len2(from[a] - centre[a], from[b] - centre[b]);
        let r1 = len2(to[a] - centre[a], to[b] - centre[b]);
        let sweep = if clockwise {
            -sweep_rad.abs()
        } else {
            sweep_rad.abs()
        };
        ArcGeometry {
            from,
            to,
            centre,
            axes,
            r0,
            r1,
            sweep,
        }
    }

    /// Point at fraction `t` (0..=1) of the sweep; radius and the normal axis
    /// change linearly with angle. `t >= 1` returns `to` exactly.
    pub fn point_at(&self, t: f64) -> Point {
        if t >= 1.0 {
            return self.to;
        }
        if t <= 0.0 {
            return self.from;
        }
        let (s, c) = (self.sweep * t).sin_cos();
        self.point_rot(t, c, s)
    }

    /// Point at fraction `t` given cos/sin of the angle travelled.
    #[inline]
    fn point_rot(&self, t: f64, c: f64, s: f64) -> Point {
        let (a, b, n) = self.axes;
        let u0 = self.from[a] - self.centre[a];
        let v0 = self.from[b] - self.centre[b];
        let k = if self.r0 > 0.0 {
            (self.r0 + (self.r1 - self.r0) * t) / self.r0
        } else {
            1.0
        };
        let mut p = [0.0; 3];
        p[a] = self.centre[a] + k * (u0 * c - v0 * s);
        p[b] = self.centre[b] + k * (u0 * s + v0 * c);
        p[n] = self.from[n] + (self.to[n] - self.from[n]) * t;
        p
    }

    /// Radius to size chords with: the larger radius for a circle; for a
    /// spiral r(φ) = r0 + kφ the chord midpoint deviates by about
    /// Δφ²·|P''|/8 with |P''| = sqrt(r² + 4k²), so that is used instead.
    pub fn effective_radius(&self) -> f64 {
        let r = self.r0.max(self.r1);
        let sweep = self.sweep.abs();
        if self.r0 == self.r1 || sweep == 0.0 {
            return r;
        }
        let k = (self.r1 - self.r0) / sweep;
        (r * r + 4.0 * k * k).sqrt()
    }

    /// Path length (helix: in-plane length and normal travel combined).
    pub fn length(&self) -> f64 {
        let (_, _, n) = self.axes;
        let planar = 0.5 * (self.r0 + self.r1) * self.sweep.abs();
        len2(planar, self.to[n] - self.from[n])
    }

    /// Exact axis-aligned bounds: end points plus every crossing of the
    /// plane's axis directions within the sweep.
    pub fn bounds(&self) -> (Point, Point) {
        let (a, b, _) = self.axes;
        let mut lo = [0.0; 3];
        let mut hi = [0.0; 3];
        for i in 0..3 {
            lo[i] = self.from[i].min(self.to[i]);
            hi[i] = self.from[i].max(self.to[i]);
        }
        let total = self.sweep.abs();
        if total == 0.0 {
            return (lo, hi);
        }
        let alpha0 = (self.from[b] - self.centre[b]).atan2(self.from[a] - self.centre[a]);
        for q in 0..4 {
            let phi = f64::from(q) * FRAC_PI_2;
            let mut delta = if self.sweep > 0.0 {
                phi - alpha0
            } else {
                alpha0 - phi
            }
            .rem_euclid(TAU);
            while delta <= total {
                let t = delta / total;
                let r = self.r0 + (self.r1 - self.r0) * t;
                let (s, c) = phi.sin_cos();
                // Cardinal directions: use exact 0/±1 to keep extrema exact.
                let (c, s) = (c.round(), s.round());
                let pa = self.centre[a] + r * c;
                let pb = self.centre[b] + r * s;
                lo[a] = lo[a].min(pa);
                hi[a] = hi[a].max(pa);
                lo[b] = lo[b].min(pb);
                hi[b] = hi[b].max(pb);
                delta += TAU;
            }
        }
        (lo, hi)
    }
}

/// Number of chords needed so that no chord of an arc of radius `radius`
/// deviates from it by more than `tolerance` (sagitta `r (1 - cos(θ/2))`),
/// with at most a quarter turn per chord. At least 1.
pub fn segments_for(radius: f64, sweep_rad: f64, tolerance: f64) -> u64 {
    let tol = sanitize(tolerance);
    let sweep = sweep_rad.abs();
    if radius.is_nan() || radius <= 0.0 || !sweep.is_finite() || sweep == 0.0 {
        return 1;
    }
    let max_step = if tol >= radius {
        FRAC_PI_2
    } else {
        (2.0 * (1.0 - tol / radius).acos()).min(FRAC_PI_2)
    };
    let n = (sweep / max_step).ceil();
    if n < 1.0 {
        1
    } else if n > 1e12 {
        1_000_000_000_000
    } else {
        n as u64
    }
}

/// Segments `m` becomes when linearised at `tolerance_mm`: 1 for a rapid or straight move, the
/// number of chords [`linearise`] makes of an arc (computed from its radius, sweep and the
/// tolerance, without making them), 0 for anything that does not move.
#[inline]
pub fn segments_of(m: &Motion, tolerance_mm: f64) -> u64 {
    match m {
        Motion::Rapid { .. } | Motion::Linear { .. } | Motion::Probe { .. } => 1,
        Motion::Arc { .. } => ArcGeometry::from_motion(m).map_or(1, |g| {
            segments_for(g.effective_radius(), g.sweep, tolerance_mm)
        }),
        _ => 0,
    }
}

/// The work budget [`crate::analyse`] applies by default, in segments (see [`WorkBudget`]).
pub const DEFAULT_MAX_SEGMENTS: u64 = 100_000_000;

/// How much work a program may cause: at most `limit` segments (moves, and the chords of arcs
/// at `tolerance_mm`), counted as the motions arrive, before any chord is made. Streaming
/// consumers stay flat in memory whatever the program; the budget bounds their time, and a
/// short `G2 I400000 P10000` (3 x 10^8 chords) is refused at its line instead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorkBudget {
    limit: u64,
    tolerance_mm: f64,
    used: u64,
}

impl WorkBudget {
    pub fn new(limit: u64, tolerance_mm: f64) -> WorkBudget {
        WorkBudget {
            limit,
            tolerance_mm: sanitize(tolerance_mm),
            used: 0,
        }
    }

    /// The most segments allowed.
    pub fn limit(&self) -> u64 {
        self.limit
    }

    /// Segments counted so far.
    pub fn used(&self) -> u64 {
        self.used
    }

    /// Counts `m`'s segments; an [`ErrorKind::Budget`] error at its line once the total would
    /// pass the limit (nothing is counted then).
    #[inline]
    pub fn charge(&mut self, m: &Motion) -> Result<(), GcodeError> {
        let n = segments_of(m, self.tolerance_mm);
        let total = self.used.saturating_add(n);
        if total > self.limit {
            return Err(self.exceeded(m, n));
        }
        self.used = total;
        Ok(())
    }

    /// The error of [`WorkBudget::charge`], out of line: charging runs once per motion.
    #[cold]
    fn exceeded(&self, m: &Motion, n: u64) -> GcodeError {
        GcodeError {
            line: m.line(),
            column: 1,
            kind: ErrorKind::Budget,
            message: format!(
                "work budget exceeded: this move makes {n} segments (arcs as chords of {} mm) \
                     on top of the {} before it, more than the budget of {} segments",
                self.tolerance_mm, self.used, self.limit
            ),
        }
    }
}

/// Passes `motions` through, charging each to `budget` first: the motion that would exceed it
/// becomes an [`ErrorKind::Budget`] error and ends the stream. Put it before [`linearise`] so a
/// huge arc is refused before its first chord.
pub fn budgeted<I>(motions: I, budget: WorkBudget) -> Budgeted<I>
where
    I: Iterator<Item = Result<Motion, GcodeError>>,
{
    Budgeted {
        inner: motions,
        budget,
        failed: false,
    }
}

/// Iterator returned by [`budgeted`].
pub struct Budgeted<I> {
    inner: I,
    budget: WorkBudget,
    failed: bool,
}

impl<I> Budgeted<I> {
    /// The budget and what has been counted so far.
    pub fn budget(&self) -> &WorkBudget {
        &self.budget
    }
    /// The wrapped iterator (e.g. to read an interpreter's warnings).
    pub fn inner(&self) -> &I {
        &self.inner
    }
    /// The wrapped iterator, to give it what it waits for (a probe's result).
    pub fn inner_mut(&mut self) -> &mut I {
        &mut self.inner
    }
    pub fn into_inner(self) -> I {
        self.inner
    }
}

impl<I> Iterator for Budgeted<I>
where
    I: Iterator<Item = Result<Motion, GcodeError>>,
{
    type Item = Result<Motion, GcodeError>;

    #[inline]
    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let item = self.inner.next()?;
        if let Ok(m) = &item {
            if let Err(e) = self.budget.charge(m) {
                self.failed = true;
                return Some(Err(e));
            }
        }
        Some(item)
    }
}

#[inline]
fn sanitize(tolerance: f64) -> f64 {
    if tolerance >= MIN_TOLERANCE_MM {
        tolerance
    } else {
        MIN_TOLERANCE_MM
    }
}

/// Turns every [`Motion::Arc`] into [`Motion::Linear`] chords whose points lie
/// on the arc (within `tolerance_mm` of it everywhere between), ending exactly
/// at the arc's `to`. Other motions and errors pass through unchanged.
/// Streaming: one arc in flight, no allocation.
pub fn linearise<I>(motions: I, tolerance_mm: f64) -> Linearise<I>
where
    I: Iterator<Item = Result<Motion, GcodeError>>,
{
    Linearise {
        inner: motions,
        tolerance: sanitize(tolerance_mm),
        arc: None,
    }
}

/// Iterator returned by [`linearise`].
pub struct Linearise<I> {
    inner: I,
    tolerance: f64,
    arc: Option<ArcRun>,
}

struct ArcRun {
    to: Point,
    plane: Plane,
    line: u32,
    feed: f64,
    n: u64,
    k: u64,
    prev: Point,
    // Precomputed per arc so that a chord costs a rotation and a few FMAs:
    // start vector from the centre, centre, radius growth per unit t
    // (spirals), normal-axis start and rise, 1/n.
    u0: f64,
    v0: f64,
    ca: f64,
    cb: f64,
    grow: f64,
    n0: f64,
    rise: f64,
    inv_n: f64,
    // Rotation of one step and the running rotation (cos, sin).
    cd: f64,
    sd: f64,
    c: f64,
    s: f64,
    step: f64,
}

/// Re-anchor the running rotation with sin_cos this often, so that the
/// rounding drift of the recurrence stays far below any tolerance.
const REANCHOR: u64 = 64;

impl ArcRun {
    fn new(g: &ArcGeometry, plane: Plane, line: u32, feed: f64, tolerance: f64) -> Self {
        let n = segments_for(g.effective_radius(), g.sweep, tolerance);
        let step = g.sweep / n as f64;
        let (sd, cd) = step.sin_cos();
        let (a, b, nn) = g.axes;
        ArcRun {
            to: g.to,
            plane,
            line,
            feed,
            n,
            k: 0,
            prev: g.from,
            u0: g.from[a] - g.centre[a],
            v0: g.from[b] - g.centre[b],
            ca: g.centre[a],
            cb: g.centre[b],
            grow: if g.r0 > 0.0 {
                (g.r1 - g.r0) / g.r0
            } else {
                0.0
            },
            n0: g.from[nn],
            rise: g.to[nn] - g.from[nn],
            inv_n: 1.0 / n as f64,
            cd,
            sd,
            c: 1.0,
            s: 0.0,
            step,
        }
    }

    #[inline]
    fn next_segment(&mut self) -> Motion {
        self.k += 1;
        let to = if self.k >= self.n {
            self.to
        } else {
            if self.k % REANCHOR == 0 {
                let (s, c) = (self.step * self.k as f64).sin_cos();
                self.c = c;
                self.s = s;
            } else {
                let c = self.c * self.cd - self.s * self.sd;
                let s = self.s * self.cd + self.c * self.sd;
                self.c = c;
                self.s = s;
            }
            let t = self.k as f64 * self.inv_n;
            let scale = 1.0 + self.grow * t;
            let pa = self.ca + scale * (self.u0 * self.c - self.v0 * self.s);
            let pb = self.cb + scale * (self.u0 * self.s + self.v0 * self.c);
            let pn = self.n0 + self.rise * t;
            // Build the point whole: stores through run-time indices followed
            // by a 16-byte load stalled store forwarding (half the chord time).
            match self.plane {
                Plane::XY => [pa, pb, pn],
                Plane::ZX => [pb, pn, pa],
                Plane::YZ => [pn, pa, pb],
            }
        };
        let from = self.prev;
        self.prev = to;
        Motion::Linear {
            line: self.line,
            from,
            to,
            feed_mm_min: self.feed,
            a: None,
        }
    }
}

impl<I> Linearise<I> {
    /// The tolerance in use (after raising to [`MIN_TOLERANCE_MM`]).
    pub fn tolerance(&self) -> f64 {
        self.tolerance
    }
    /// The wrapped iterator (e.g. to read an interpreter's warnings).
    pub fn inner(&self) -> &I {
        &self.inner
    }
    /// The wrapped iterator, to give it what it waits for (a probe's result).
    pub fn inner_mut(&mut self) -> &mut I {
        &mut self.inner
    }
    /// The wrapped iterator; an arc in progress is dropped.
    pub fn into_inner(self) -> I {
        self.inner
    }
}

impl<I> Iterator for Linearise<I>
where
    I: Iterator<Item = Result<Motion, GcodeError>>,
{
    type Item = Result<Motion, GcodeError>;

    #[inline]
    fn next(&mut self) -> Option<Self::Item> {
        if let Some(run) = &mut self.arc {
            let m = run.next_segment();
            if run.k >= run.n {
                self.arc = None;
            }
            return Some(Ok(m));
        }
        let item = self.inner.next()?;
        let m = match item {
            Ok(m) => m,
            Err(e) => return Some(Err(e)),
        };
        let (line, feed, plane) = match &m {
            Motion::Arc {
                line,
                feed_mm_min,
                plane,
                ..
            } => (*line, *feed_mm_min, *plane),
            _ => return Some(Ok(m)),
        };
        let Some(g) = ArcGeometry::from_motion(&m) else {
            return Some(Ok(m));
        };
        let mut run = ArcRun::new(&g, plane, line, feed, self.tolerance);
        let first = run.next_segment();
        if run.k < run.n {
            self.arc = Some(run);
        }
        Some(Ok(first))
    }
}
