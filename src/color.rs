//! The exact piecewise sRGB transfer curve (IEC 61966-2-1). All shading is linear;
//! PNG inputs and outputs are sRGB-encoded except NeRFactor's `albedo.png`. And the luminance of
//! a linear colour.

use glam::Vec3;

/// Luminance of a linear Rec. 709 / sRGB colour (the Rec. 709 weights, which sRGB's primaries share).
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.2126, 0.7152, 0.0722))
}

/// sRGB-encoded value in [0, 1] to linear.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear value to sRGB encoding; negative input maps to 0, values above 1 are not clipped.
pub fn linear_to_srgb(c: f32) -> f32 {
    let c = c.max(0.0);
    if c <= 0.0031308 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_every_8bit_code() {
        for code in 0..=255u32 {
            let s = code as f32 / 255.0;
            let back = linear_to_srgb(srgb_to_linear(s));
            assert!((back - s).abs() < 1e-5, "code {code}: {s} -> {back}");
        }
    }

    #[test]
    fn curve_is_continuous_at_the_knee() {
        // The two pieces meet at 0.04045 / 0.0031308 to within float precision.
        let below = srgb_to_linear(0.04045);
        let above = ((0.04045f32 + 0.055) / 1.055).powf(2.4);
        assert!((below - above).abs() < 1e-6);
        assert!((srgb_to_linear(0.5) - 0.214_041_14).abs() < 1e-6);
        assert!((linear_to_srgb(0.18) - 0.461_356_1).abs() < 1e-5);
    }
}
