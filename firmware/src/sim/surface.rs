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
