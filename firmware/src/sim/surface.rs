//! The simulated bed's surface under a probe: a tilted, warped plane, so a probe triggers at
//! the true height under it and a mesh can be checked against the truth.
//!
//! Height above the probe's flat trigger coordinate, at bed point (x, y):
//! `h(x, y) = tilt_x · x + tilt_y · y + warp · sin(2π x / period) · sin(2π y / period)`
//! (0 at the origin; `warp` is the bump amplitude in mm, `period` its wavelength in mm). The
//! probe sits at the toolhead's X, Y plus its offsets; the toolhead's X and Y are world
//! coordinates ([`Coord`]), read at the sample's time like every endstop.
//!
//! Text form (`--bed-surface`): `PIN=XCOORD,YCOORD,X_OFFSET,Y_OFFSET,TILT_X,TILT_Y,WARP,PERIOD`.

use super::world::Coord;

/// `--bed-surface`: the surface probe input PIN touches.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceSpec {
    /// The probe's input pin (an `--endstop` or a `--bltouch` sensor pin).
    pub pin: u8,
    /// The toolhead's X and Y in the world.
    pub x: Coord,
    pub y: Coord,
    /// Where the probe sits relative to the nozzle.
    pub offset: [f64; 2],
    /// Surface slope along X and Y (mm per mm).
    pub tilt: [f64; 2],
    /// Bump amplitude (mm).
    pub warp: f64,
    /// Bump wavelength (mm, > 0).
    pub period: f64,
}

impl SurfaceSpec {
    /// The surface height at bed point (x, y).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let k = std::f64::consts::TAU / self.period;
        self.tilt[0] * x + self.tilt[1] * y + self.warp * (k * x).sin() * (k * y).sin()
    }

    /// The surface height under the probe with the toolhead at (x, y).
    pub fn under_probe(&self, x: f64, y: f64) -> f64 {
        self.height(x + self.offset[0], y + self.offset[1])
    }

    /// Parses the text form; never panics.
    pub fn parse(s: &str) -> Result<SurfaceSpec, String> {
        const FORM: &str = "expected PIN=XCOORD,YCOORD,X_OFFSET,Y_OFFSET,TILT_X,TILT_Y,WARP,PERIOD";
        let (pin, rest) = s.split_once('=').ok_or(FORM)?;
        let f: Vec<&str> = rest.split(',').map(str::trim).collect();
        let [x, y, xo, yo, tx, ty, warp, period] = f.as_slice() else {
            return Err(FORM.into());
        };
        let num = |t: &str, what: &str| -> Result<f64, String> {
            t.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("{what} `{t}` is not a finite number"))
        };
        let period = num(period, "period")?;
        if period <= 0.0 {
            return Err(format!("period must be above 0, got {period}"));
        }
        Ok(SurfaceSpec {
            pin: super::cli::parse_pin(pin.trim())?,
            x: Coord::parse(x).map_err(|e| e.to_string())?,
            y: Coord::parse(y).map_err(|e| e.to_string())?,
            offset: [num(xo, "x offset")?, num(yo, "y offset")?],
            tilt: [num(tx, "tilt x")?, num(ty, "tilt y")?],
            warp: num(warp, "warp")?,
            period,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_computes_the_height() {
        let s = SurfaceSpec::parse("PA4=x,y,-10,5,0.01,-0.002,0.1,40").unwrap();
        assert_eq!(
            (s.offset, s.tilt, s.warp, s.period),
            ([-10.0, 5.0], [0.01, -0.002], 0.1, 40.0)
        );
        assert_eq!(s.height(0.0, 0.0), 0.0);
        // sin(π/2)² = 1 at (10, 10).
        assert!((s.height(10.0, 10.0) - (0.1 - 0.02 + 0.1)).abs() < 1e-12);
        assert!((s.under_probe(20.0, 5.0) - s.height(10.0, 10.0)).abs() < 1e-12);
        assert!(SurfaceSpec::parse("PA4=x,y,0,0,0,0,0,0")
            .unwrap_err()
            .contains("period"));
        assert!(SurfaceSpec::parse("PA4=x,y,0,0,0").is_err());
        assert!(SurfaceSpec::parse("PA4=x,y,0,0,nan,0,0,1").is_err());
    }

    proptest::proptest! {
        #[test]
        fn parsing_never_panics(s in ".{0,60}") {
            let _ = SurfaceSpec::parse(&s);
        }
    }
}

/// `--gantry`: the probe on input PIN rides a gantry lifted by several Z motors, so its height
/// is not one axis but the gantry's at the probe: with two motors the line through their
/// (position, height) points, with three the plane through them, with four (the corners of a
/// rectangle) the bilinear surface through them, at the probe's X, Y.
///
/// Text form: `PIN=XCOORD,YCOORD,X_OFFSET,Y_OFFSET,AXIS:X:Y,AXIS:X:Y[,AXIS:X:Y[,AXIS:X:Y]]`.
#[derive(Debug, Clone, PartialEq)]
pub struct GantrySpec {
    pub pin: u8,
    pub x: Coord,
    pub y: Coord,
    pub offset: [f64; 2],
    /// (world axis of the motor, its X, Y).
    pub motors: Vec<(String, [f64; 2])>,
}

impl GantrySpec {
    /// The gantry's height at (x, y) given each motor's height (in `motors` order); `None`
    /// for a degenerate layout.
    pub fn height(&self, x: f64, y: f64, z: &[f64]) -> Option<f64> {
        let p: Vec<[f64; 2]> = self.motors.iter().map(|m| m.1).collect();
        match (p.as_slice(), z) {
            ([a, b], [za, zb]) => {
                let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
                let len2 = dx * dx + dy * dy;
                (len2 > 0.0).then(|| za + (zb - za) * ((x - a[0]) * dx + (y - a[1]) * dy) / len2)
            }
            ([a, b, c], [za, zb, zc]) => {
                // Barycentric weights of (x, y) in triangle a b c.
                let det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1]);
                if det.abs() < 1e-12 {
                    return None;
                }
                let wa = ((b[1] - c[1]) * (x - c[0]) + (c[0] - b[0]) * (y - c[1])) / det;
                let wb = ((c[1] - a[1]) * (x - c[0]) + (a[0] - c[0]) * (y - c[1])) / det;
                Some(wa * za + wb * zb + (1.0 - wa - wb) * zc)
            }
            (corners @ [_, _, _, _], [_, _, _, _]) => {
                // A rectangle: u, v across it; each corner weighs by its side.
                let x0 = corners.iter().map(|c| c[0]).fold(f64::INFINITY, f64::min);
                let x1 = corners.iter().map(|c| c[0]).fold(f64::NEG_INFINITY, f64::max);
                let y0 = corners.iter().map(|c| c[1]).fold(f64::INFINITY, f64::min);
                let y1 = corners.iter().map(|c| c[1]).fold(f64::NEG_INFINITY, f64::max);
                if x1 - x0 <= 0.0 || y1 - y0 <= 0.0 {
                    return None;
                }
                let (u, v) = ((x - x0) / (x1 - x0), (y - y0) / (y1 - y0));
                let mut h = 0.0;
                for (c, zc) in corners.iter().zip(z) {
                    let wu = if c[0] == x1 { u } else { 1.0 - u };
                    let wv = if c[1] == y1 { v } else { 1.0 - v };
                    h += wu * wv * zc;
                }
                Some(h)
            }
            _ => None,
        }
    }

    /// Parses the text form; never panics.
    pub fn parse(s: &str) -> Result<GantrySpec, String> {
        const FORM: &str =
            "expected PIN=XCOORD,YCOORD,X_OFFSET,Y_OFFSET,AXIS:X:Y,AXIS:X:Y[,AXIS:X:Y[,AXIS:X:Y]]";
        let (pin, rest) = s.split_once('=').ok_or(FORM)?;
        let f: Vec<&str> = rest.split(',').map(str::trim).collect();
        let [x, y, xo, yo, motors @ ..] = f.as_slice() else {
            return Err(FORM.into());
        };
        if !(2..=4).contains(&motors.len()) {
            return Err(format!("a gantry has 2 to 4 motors, got {}", motors.len()));
        }
        let num = |t: &str| -> Result<f64, String> {
            t.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("`{t}` is not a finite number"))
        };
        let motors = motors
            .iter()
            .map(|m| match m.split(':').collect::<Vec<_>>().as_slice() {
                [axis, mx, my] if !axis.is_empty() => Ok((axis.to_string(), [num(mx)?, num(my)?])),
                _ => Err(format!("motor `{m}`: expected AXIS:X:Y")),
            })
            .collect::<Result<Vec<_>, String>>()?;
        Ok(GantrySpec {
            pin: super::cli::parse_pin(pin.trim())?,
            x: Coord::parse(x).map_err(|e| e.to_string())?,
            y: Coord::parse(y).map_err(|e| e.to_string())?,
            offset: [num(xo)?, num(yo)?],
            motors,
        })
    }
}

#[cfg(test)]
mod gantry_tests {
    use super::*;

    #[test]
    fn two_three_and_four_motor_gantries() {
        let g = GantrySpec::parse("PA4=x,y,0,0,z:0:10,z1:20:10").unwrap();
        assert_eq!(g.height(5.0, 3.0, &[1.0, 2.0]), Some(1.25));
        let g = GantrySpec::parse("PA4=x,y,1,2,z:0:0,z1:20:0,z2:10:20").unwrap();
        assert_eq!(g.offset, [1.0, 2.0]);
        let h = g.height(10.0, 20.0, &[0.0, 0.0, 3.0]).unwrap();
        assert!((h - 3.0).abs() < 1e-12);
        let h = g.height(10.0, 0.0, &[1.0, 3.0, 0.0]).unwrap();
        assert!((h - 2.0).abs() < 1e-12);
        let g = GantrySpec::parse("PA4=x,y,0,0,z:0:0,z1:0:10,z2:20:10,z3:20:0").unwrap();
        // Bilinear: the centre is the corners' mean, an edge's middle its two corners' mean.
        assert_eq!(g.height(10.0, 5.0, &[0.0, 1.0, 2.0, 5.0]), Some(2.0));
        assert_eq!(g.height(0.0, 5.0, &[0.0, 1.0, 2.0, 5.0]), Some(0.5));
        assert!(GantrySpec::parse("PA4=x,y,0,0,z:0:0")
            .unwrap_err()
            .contains("2 to 4 motors"));
        assert!(GantrySpec::parse("PA4=x,y,0,0,z:0,z1:1:1")
            .unwrap_err()
            .contains("AXIS:X:Y"));
    }

    proptest::proptest! {
        #[test]
        fn parsing_never_panics(s in ".{0,60}") {
            let _ = GantrySpec::parse(&s);
        }
    }
}
