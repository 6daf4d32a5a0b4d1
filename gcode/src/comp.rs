//! Cutter radius compensation (G41/G42, G41.1/G42.1, G40) in the XY plane,
//! following the rules of LinuxCNC's interpreter so the compensated path is
//! the one `rs274` makes:
//!
//! * Entry (the first move after G41/G42): a straight move to a point one
//!   radius beside the programmed end, perpendicular to the move; the move
//!   must be longer than the radius. (An arc as entry move is refused.)
//! * Every later move is offset by the radius. A move's end point is not
//!   final until the next move is known, so the compensated moves wait in
//!   [`Comp::held`] (with anything the program asked for meanwhile) and are
//!   released when the corner they end in is resolved:
//!   * convex corner (the tool goes round the outside): an arc round the
//!     programmed corner is inserted (a straight rapid for G0);
//!   * concave corner: the waiting moves end where the new move starts
//!     (line-line, arc-line, line-arc, arc-arc intersections), and a move
//!     that would have to run backwards is a gouging error.
//! * G40: the waiting moves are released as they are; the next move (which
//!   must be straight) leaves from the compensated point.
//!
//! Angles are compared with LinuxCNC's 0.05 rad corner tolerance.

use crate::{ErrorKind, Motion, Point};
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// LinuxCNC's TOLERANCE_CONCAVE_CORNER (radians).
const SMALL: f64 = 0.05;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Side {
    Left,
    Right,
}

/// A queued event; moves keep what the gouge checks need.
#[derive(Debug, Clone)]
pub(crate) struct Held {
    pub m: Motion,
    /// Straight moves: the direction LinuxCNC records for the move.
    dir: [f64; 2],
    /// Arcs: the programmed sweep (signed, rad), 0 for inserted corner arcs.
    orig_sweep: f64,
    /// Arcs: +turns counter-clockwise, -turns clockwise.
    turn: i32,
}

#[derive(Debug, Clone, Default)]
pub(crate) struct Comp {
    pub side: Option<Side>,
    pub radius: f64,
    /// No move made since G41/G42: the next one is the entry move.
    pub first: bool,
    /// Where the tool is in XY (its programmed point is the interpreter's
    /// position) while compensation is on.
    pub tool: [f64; 2],
    /// Moves whose end points wait for the next move, and events after them.
    pub held: Vec<Held>,
    /// Start of the waiting moves (LinuxCNC's `endpoint`), for gouge checks.
    endpoint: Option<[f64; 2]>,
    /// After G40 the next move must be straight (LinuxCNC).
    pub arc_not_allowed: bool,
    /// After G40: the tool's XY, where the next move starts from.
    pub detached: Option<[f64; 2]>,
    /// While a line runs (from [`Comp::begin_line`]), what [`Comp::rollback`] restores.
    undo: Option<Box<Undo>>,
}

/// The state before a line: all but the held events, how many were held, and those events
/// themselves only once the line changes or releases them. A line that only adds events (as
/// every line without a move does) so costs the same however many wait: copying them all for
/// every line made a program of 1,000 messages behind a held move quadratic (found by the
/// grammar fuzz target's CPU budget).
#[derive(Debug, Clone)]
struct Undo {
    before: Comp,
    held_len: usize,
    held: Option<Vec<Held>>,
}

/// An error of this module: message (the caller adds line and column).
pub(crate) type CompError = (ErrorKind, String);

fn gouge(msg: &str) -> CompError {
    (ErrorKind::Invalid, msg.to_string())
}

impl Comp {
    /// A line starts: until [`Comp::commit`], [`Comp::rollback`] undoes what it does.
    pub fn begin_line(&mut self) {
        let before = Comp {
            side: self.side,
            radius: self.radius,
            first: self.first,
            tool: self.tool,
            held: Vec::new(),
            endpoint: self.endpoint,
            arc_not_allowed: self.arc_not_allowed,
            detached: self.detached,
            undo: None,
        };
        self.undo = Some(Box::new(Undo {
            before,
            held_len: self.held.len(),
            held: None,
        }));
    }

    /// The line succeeded: what it did stays.
    pub fn commit(&mut self) {
        self.undo = None;
    }

    /// The line failed or was skipped: back to the state before it.
    pub fn rollback(&mut self) {
        if let Some(u) = self.undo.take() {
            let Undo {
                before,
                held_len,
                held,
            } = *u;
            let held = match held {
                Some(h) => h,
                None => {
                    let mut h = std::mem::take(&mut self.held);
                    h.truncate(held_len);
                    h
                }
            };
            *self = Comp { held, ..before };
        }
    }

    /// Saves the events held before this line, before the line changes or releases them.
    fn save_held(&mut self) {
        if let Some(u) = self.undo.as_mut() {
            if u.held.is_none() {
                u.held = Some(self.held[..u.held_len.min(self.held.len())].to_vec());
            }
        }
    }

    /// Compensation is on with a radius: moves are offset.
    #[inline]
    pub fn active(&self) -> bool {
        self.side.is_some() && self.radius > 0.0
    }

    fn inside_arc(&self, turn: i32) -> bool {
        matches!(
            (self.side, turn > 0),
            (Some(Side::Left), true) | (Some(Side::Right), false)
        )
    }

    /// Holds any event (behind the waiting moves).
    pub fn hold_event(&mut self, m: Motion) {
        self.held.push(Held {
            m,
            dir: [0.0; 2],
            orig_sweep: 0.0,
            turn: 0,
        });
    }

    fn hold_move(&mut self, m: Motion, dir: [f64; 2], orig_sweep: f64, turn: i32) {
        self.held.push(Held {
            m,
            dir,
            orig_sweep,
            turn,
        });
    }

    /// Releases everything waiting, unchanged (LinuxCNC `dequeue_canons`).
    pub fn release(&mut self, out: &mut Vec<Motion>) {
        self.save_held();
        self.endpoint = None;
        out.extend(self.held.drain(..).map(|h| h.m));
    }

    /// Moves the XY end of every waiting move to `to`, checks that none of
    /// them now runs backwards, and releases them (`move_endpoint_and_flush`).
    fn move_end_and_release(
        &mut self,
        to: [f64; 2],
        inch: bool,
        out: &mut Vec<Motion>,
    ) -> Result<(), CompError> {
        if self.held.is_empty() {
            return Ok(());
        }
        self.save_held();
        let valid = self.endpoint;
        let mut prev_end: Option<Point> = None;
        for h in &mut self.held {
            match &mut h.m {
                Motion::Arc {
                    from,
                    to: end,
                    centre,
                    clockwise,
                    turns,
                    sweep_rad,
                    ..
                } => {
                    let r1 = (end[0] - centre[0]).hypot(end[1] - centre[1]);
                    let r2 = (to[0] - centre[0]).hypot(to[1] - centre[1]);
                    if (r1 - r2).abs() > 0.01 {
                        return Err(gouge(
                            "cutter compensation made an arc with mismatched radii",
                        ));
                    }
                    if let Some(ep) = valid {
                        let l2 = find_turn(ep, [centre[0], centre[1]], h.turn, to);
                        let tol = if inch { 0.001 } else { 0.0254 };
                        if h.orig_sweep != 0.0 && l2.abs() > h.orig_sweep.abs() + tol {
                            return Err(gouge(
                                "Arc move in concave corner cannot be reached by the tool without gouging",
                            ));
                        }
                    }
                    if let Some(p) = prev_end {
                        *from = p;
                    }
                    end[0] = to[0];
                    end[1] = to[1];
                    let t = if *clockwise {
                        -(*turns as i32)
                    } else {
                        *turns as i32
                    };
                    *sweep_rad = find_turn([from[0], from[1]], [centre[0], centre[1]], t, to).abs();
                    prev_end = Some(*end);
                }
                Motion::Rapid { from, to: end, .. } | Motion::Linear { from, to: end, .. } => {
                    if let Some(ep) = valid {
                        let dot = h.dir[0] * (to[0] - ep[0]) + h.dir[1] * (to[1] - ep[1]);
                        if dot < 0.0 {
                            return Err(gouge(if matches!(h.m, Motion::Rapid { .. }) {
                                "Straight traverse in concave corner cannot be reached by the tool without gouging"
                            } else {
                                "Straight feed in concave corner cannot be reached by the tool without gouging"
                            }));
                        }
                    }
                    if let Some(p) = prev_end {
                        *from = p;
                    }
                    end[0] = to[0];
                    end[1] = to[1];
                    prev_end = Some(*end);
                }
                _ => {}
            }
        }
        self.release(out);
        self.endpoint = Some(to);
        Ok(())
    }

    /// The first waiting move, if it is an arc: (end, centre, turn).
    fn front_arc(&self) -> Option<([f64; 2], [f64; 2], i32)> {
        match self.held.first() {
            Some(Held {
                m: Motion::Arc { to, centre, .. },
                turn,
                ..
            }) => Some(([to[0], to[1]], [centre[0], centre[1]], *turn)),
            _ => None,
        }
    }

    /// G40: releases the waiting moves; the next move leaves from the
    /// compensated point.
    pub fn off(&mut self, prog: Point, out: &mut Vec<Motion>) {
        if self.active() && !self.first {
            self.release(out);
            self.arc_not_allowed = true;
            if self.tool != [prog[0], prog[1]] {
                self.detached = Some(self.tool);
            }
        }
        self.side = None;
        self.first = true;
    }

    /// A compensated straight move from the programmed point `prog` to the
    /// programmed `target`. `rapid`: G0. Released events go to `out`.
    #[allow(clippy::too_many_arguments)]
    pub fn straight(
        &mut self,
        line: u32,
        rapid: bool,
        feed: f64,
        prog: Point,
        target: Point,
        inch: bool,
        out: &mut Vec<Motion>,
    ) -> Result<(), CompError> {
        let r = self.radius;
        let left = self.side == Some(Side::Left);
        let c = [self.tool[0], self.tool[1], prog[2]];
        let make = |from: Point, to: Point| {
            if rapid {
                Motion::Rapid {
                    line,
                    from,
                    to,
                    a: None,
                }
            } else {
                Motion::Linear {
                    line,
                    from,
                    to,
                    feed_mm_min: feed,
                    a: None,
                }
            }
        };
        let (px, py) = (target[0], target[1]);
        if self.first {
            let distance = (px - c[0]).hypot(py - c[1]);
            if distance <= r {
                return Err(gouge(
                    "Length of cutter compensation entry move is not greater than the tool radius",
                ));
            }
            let alpha = (py - c[1]).atan2(px - c[0]) + if left { FRAC_PI_2 } else { -FRAC_PI_2 };
            let end = [px + r * alpha.cos(), py + r * alpha.sin(), target[2]];
            self.endpoint = Some([c[0], c[1]]);
            // Right after G40 the tool is still at the compensated point.
            let from = self.detached.take().map_or(c, |d| [d[0], d[1], c[2]]);
            self.hold_move(make(from, end), [alpha.cos(), alpha.sin()], 0.0, 0);
            self.first = false;
            self.tool = [end[0], end[1]];
            return Ok(());
        }
        let (opx, opy) = (prog[0], prog[1]);
        if px == opx && py == opy {
            // No XY motion: queued behind the waiting moves, which may still
            // move its XY (LinuxCNC).
            let end = [c[0], c[1], target[2]];
            self.hold_move(make(c, end), [0.0, 0.0], 0.0, 0);
            return Ok(());
        }
        let mut theta = (c[1] - opy).atan2(c[0] - opx);
        let mut alpha = (py - opy).atan2(px - opx);
        let (beta, gamma) = if left {
            if theta < alpha {
                theta += TAU;
            }
            (theta - alpha - FRAC_PI_2, FRAC_PI_2)
        } else {
            if alpha < theta {
                alpha += TAU;
            }
            (alpha - theta - FRAC_PI_2, -FRAC_PI_2)
        };
        let end = [
            px + r * (alpha + gamma).cos(),
            py + r * (alpha + gamma).sin(),
            target[2],
        ];
        let mid = [
            opx + r * (alpha + gamma).cos(),
            opy + r * (alpha + gamma).sin(),
        ];
        let front = self.front_arc();
        let concave = !(-SMALL..=PI + SMALL).contains(&beta)
            || (beta > PI - SMALL
                && front.is_some_and(|(_, _, turn)| (left && turn < 0) || (!left && turn > 0)));
        let mut start = c;
        if !concave && beta > SMALL {
            // Convex corner: round it (G1) or cut across (G0).
            self.move_end_and_release([c[0], c[1]], inch, out)?;
            let to = [mid[0], mid[1], c[2]];
            if rapid {
                out.push(Motion::Rapid {
                    line,
                    from: c,
                    to,
                    a: None,
                });
            } else {
                out.push(corner_arc(line, c, to, [opx, opy], left, feed));
            }
            self.endpoint = Some(mid);
            start = to;
        } else if concave {
            let new_end = match front {
                None => {
                    // line -> line: back along the previous compensated move.
                    let halfcorner = (beta + PI) / 2.0;
                    if halfcorner == 0.0 {
                        return Err(gouge(
                            "Zero degree inside corner is invalid for cutter compensation",
                        ));
                    }
                    let retreat = r / halfcorner.tan();
                    [
                        c[0] + retreat * (theta + gamma).cos(),
                        c[1] + retreat * (theta + gamma).sin(),
                    ]
                }
                Some((pend, pcentre, pturn)) => {
                    // arc -> line: the previous (compensated) arc ends where
                    // the new line's offset meets it.
                    let oldrad = (pcentre[1] - pend[1]).hypot(pcentre[0] - pend[0]);
                    let base_dir = (py - opy).atan2(px - opx);
                    let theta = if pturn > 0 {
                        base_dir + FRAC_PI_2
                    } else {
                        base_dir - FRAC_PI_2
                    };
                    let phi = (pcentre[1] - opy).atan2(pcentre[0] - opx);
                    let inside = self.inside_arc(pturn);
                    let oldrad_uncomp = if inside { oldrad + r } else { oldrad - r };
                    let d = oldrad_uncomp * (theta - phi).cos();
                    let l = (if inside { d - r } else { d + r }) / oldrad;
                    if !(-1.0..=1.0).contains(&l) {
                        return Err(gouge(
                            "Arc to straight motion makes a corner the compensated tool can't fit in without gouging",
                        ));
                    }
                    let angle = if inside == (pturn > 0) {
                        -l.acos() + theta + PI
                    } else {
                        l.acos() + theta + PI
                    };
                    [
                        pcentre[0] + oldrad * angle.cos(),
                        pcentre[1] + oldrad * angle.sin(),
                    ]
                }
            };
            self.move_end_and_release(new_end, inch, out)?;
            start = [new_end[0], new_end[1], c[2]];
        } else {
            // Straight on, or a tangent arc -> line.
            self.release(out);
            self.endpoint = Some([c[0], c[1]]);
        }
        self.hold_move(make(start, end), [px - opx, py - opy], 0.0, 0);
        self.tool = [end[0], end[1]];
        Ok(())
    }

    /// A compensated arc. `programmed` is the arc through the programmed
    /// points (from [`crate::interp`]'s arc builder).
    pub fn arc(
        &mut self,
        programmed: &Motion,
        inch: bool,
        out: &mut Vec<Motion>,
    ) -> Result<(), CompError> {
        let Motion::Arc {
            line,
            from: op,
            to: pend,
            centre,
            plane,
            clockwise,
            feed_mm_min,
            turns,
            ..
        } = *programmed
        else {
            return Ok(());
        };
        let r = self.radius;
        let left = self.side == Some(Side::Left);
        let turn = if clockwise {
            -(turns as i32)
        } else {
            turns as i32
        };
        if self.first {
            return self.entry_arc(programmed, turn);
        }
        let c = [self.tool[0], self.tool[1], op[2]];
        let (cx, cy) = (centre[0], centre[1]);
        let arc_radius = (cx - pend[0]).hypot(cy - pend[1]);
        let mut theta = (c[1] - op[1]).atan2(c[0] - op[0]);
        theta = if left {
            theta - FRAC_PI_2
        } else {
            theta + FRAC_PI_2
        };
        let mut delta = (cy - op[1]).atan2(cx - op[0]);
        let alpha = if clockwise {
            delta + FRAC_PI_2
        } else {
            delta - FRAC_PI_2
        };
        let mut beta = if left { theta - alpha } else { alpha - theta };
        if beta > 1.5 * PI {
            beta -= TAU;
        } else if beta < -FRAC_PI_2 {
            beta += TAU;
        }
        let inside = self.inside_arc(turn);
        let gamma = if inside {
            if arc_radius <= r {
                return Err(gouge(
                    "Tool radius not less than arc radius with cutter radius compensation",
                ));
            }
            (cy - pend[1]).atan2(cx - pend[0])
        } else {
            delta += PI;
            (pend[1] - cy).atan2(pend[0] - cx)
        };
        let new_end = [
            pend[0] + r * gamma.cos(),
            pend[1] + r * gamma.sin(),
            pend[2],
        ];
        let orig_sweep = find_turn([op[0], op[1]], [cx, cy], turn, [pend[0], pend[1]]);
        let mut start = c;
        if !(-SMALL..=PI + SMALL).contains(&beta) || ((beta - PI).abs() < SMALL && !inside) {
            // Concave corner.
            let mid = match self.front_arc() {
                None => {
                    let cyv = arc_radius * (beta - FRAC_PI_2).sin();
                    let (dist, toward) = if inside {
                        (arc_radius - r, cyv + r)
                    } else {
                        (arc_radius + r, cyv - r)
                    };
                    let l = toward / dist;
                    if !(-1.0..=1.0).contains(&l) {
                        return Err(gouge(
                            "Arc move in concave corner cannot be reached by the tool without gouging",
                        ));
                    }
                    let angle = match (inside, turn > 0) {
                        (true, true) => theta + l.asin(),
                        (true, false) => theta - l.asin(),
                        (false, true) => theta + PI - l.asin(),
                        (false, false) => theta + PI + l.asin(),
                    };
                    [cx + dist * angle.cos(), cy + dist * angle.sin()]
                }
                Some((prev_end, prev_centre, prev_turn)) => {
                    let oldrad = (prev_centre[1] - prev_end[1]).hypot(prev_centre[0] - prev_end[0]);
                    let newrad = if inside {
                        arc_radius - r
                    } else {
                        arc_radius + r
                    };
                    let arc_cc = (prev_centre[1] - cy).hypot(prev_centre[0] - cx);
                    if oldrad == 0.0 || arc_cc == 0.0 {
                        return Err(gouge(
                            "Arc to arc motion is invalid because the arcs have the same center",
                        ));
                    }
                    let a = (oldrad * oldrad + arc_cc * arc_cc - newrad * newrad)
                        / (2.0 * oldrad * arc_cc);
                    if !(-1.0..=1.0).contains(&a) {
                        return Err(gouge(
                            "Arc to arc motion makes a corner the compensated tool can't fit in without gouging",
                        ));
                    }
                    let pullback = a.acos();
                    let cc_dir = (cy - prev_centre[1]).atan2(cx - prev_centre[0]);
                    let dir = if self.inside_arc(prev_turn) == (turn > 0) {
                        cc_dir + pullback
                    } else {
                        cc_dir - pullback
                    };
                    [
                        prev_centre[0] + oldrad * dir.cos(),
                        prev_centre[1] + oldrad * dir.sin(),
                    ]
                }
            };
            self.move_end_and_release(mid, inch, out)?;
            start = [mid[0], mid[1], c[2]];
        } else if beta > SMALL {
            // Convex: an arc round the corner, then the arc itself.
            let mid = [op[0] + r * delta.cos(), op[1] + r * delta.sin(), c[2]];
            self.release(out);
            out.push(corner_arc(line, c, mid, [op[0], op[1]], left, feed_mm_min));
            self.endpoint = Some([mid[0], mid[1]]);
            start = mid;
        } else {
            self.release(out);
            self.endpoint = Some([c[0], c[1]]);
        }
        let sweep = find_turn(
            [start[0], start[1]],
            [cx, cy],
            turn,
            [new_end[0], new_end[1]],
        )
        .abs();
        let m = Motion::Arc {
            line,
            from: start,
            to: new_end,
            centre: [cx, cy, start[2]],
            plane,
            clockwise,
            feed_mm_min,
            turns,
            sweep_rad: sweep,
        };
        self.hold_move(m, [0.0; 2], orig_sweep, turn);
        self.tool = [new_end[0], new_end[1]];
        Ok(())
    }
}

impl Comp {
    /// An arc as the entry move: it ends one radius beside the programmed
    /// end (towards or away from the centre) and starts where the tool is;
    /// its centre moves so that both ends lie on one circle.
    fn entry_arc(&mut self, programmed: &Motion, turn: i32) -> Result<(), CompError> {
        let Motion::Arc {
            line,
            to: pend,
            centre,
            plane,
            clockwise,
            feed_mm_min,
            turns,
            from,
            ..
        } = *programmed
        else {
            return Ok(());
        };
        let r = self.radius;
        let c = [self.tool[0], self.tool[1], from[2]];
        if (pend[0] - c[0]).hypot(pend[1] - c[1]) <= r {
            return Err(gouge(
                "Radius of cutter compensation entry arc is not greater than the tool radius",
            ));
        }
        let inside = self.inside_arc(turn);
        let arc_radius = (centre[0] - pend[0]).hypot(centre[1] - pend[1]);
        if inside && arc_radius <= r {
            return Err(gouge(
                "Tool radius not less than arc radius with cutter radius compensation",
            ));
        }
        let gamma = if inside {
            (centre[1] - pend[1]).atan2(centre[0] - pend[0])
        } else {
            (pend[1] - centre[1]).atan2(pend[0] - centre[0])
        };
        let end = [
            pend[0] + r * gamma.cos(),
            pend[1] + r * gamma.sin(),
            pend[2],
        ];
        // Right triangle: end point, new centre, middle of the chord.
        let b_len = (c[1] - end[1]).hypot(c[0] - end[0]) / 2.0;
        let ab_ang = (centre[1] - end[1]).atan2(centre[0] - end[0]);
        let a_ang = (c[1] - end[1]).atan2(c[0] - end[0]) - ab_ang;
        if a_ang.cos().abs() < 1e-6 {
            return Err(gouge(
                "Tool radius not less than arc radius with cutter radius compensation",
            ));
        }
        let c_len = b_len / a_ang.cos();
        let new_centre = [end[0] + c_len * ab_ang.cos(), end[1] + c_len * ab_ang.sin()];
        let from = self.detached.take().map_or(c, |d| [d[0], d[1], c[2]]);
        let sweep = find_turn([c[0], c[1]], new_centre, turn, [end[0], end[1]]);
        let m = Motion::Arc {
            line,
            from,
            to: end,
            centre: [new_centre[0], new_centre[1], from[2]],
            plane,
            clockwise,
            feed_mm_min,
            turns,
            sweep_rad: sweep.abs(),
        };
        self.hold_move(m, [0.0; 2], sweep, turn);
        self.first = false;
        self.tool = [end[0], end[1]];
        Ok(())
    }
}

/// The arc round a convex corner: about the programmed corner, clockwise
/// with the tool on the left.
fn corner_arc(
    line: u32,
    from: Point,
    to: Point,
    corner: [f64; 2],
    left: bool,
    feed: f64,
) -> Motion {
    let turn = if left { -1 } else { 1 };
    Motion::Arc {
        line,
        from,
        to,
        centre: [corner[0], corner[1], from[2]],
        plane: crate::Plane::XY,
        clockwise: left,
        feed_mm_min: feed,
        turns: 1,
        sweep_rad: find_turn([from[0], from[1]], corner, turn, [to[0], to[1]]).abs(),
    }
}

/// Signed angle (rad) from `a` to `b` about `centre`, `turn` full or
/// partial circles (> 0 counter-clockwise), as LinuxCNC's `find_turn`.
fn find_turn(a: [f64; 2], centre: [f64; 2], turn: i32, b: [f64; 2]) -> f64 {
    if turn == 0 {
        return 0.0;
    }
    let mut alpha = (a[1] - centre[1]).atan2(a[0] - centre[0]);
    let mut beta = (b[1] - centre[1]).atan2(b[0] - centre[0]);
    if turn > 0 {
        if beta <= alpha {
            beta += TAU;
        }
        beta - alpha + f64::from(turn - 1) * TAU
    } else {
        if alpha <= beta {
            alpha += TAU;
        }
        beta - alpha + f64::from(turn + 1) * TAU
    }
}
