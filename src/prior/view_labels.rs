//! The labels of one view, the type every label source returns (the IDArb network, label files,
//! the oracle, simulated IDArb): the four material maps and the mask they cover. Here, beside the
//! `Prior` trait, so that the sources that never run the network do not depend on its code.

use crate::image::Image;

/// Labels of one view, at the view's original size; values in [0, 1].
#[derive(Debug, Clone)]
pub struct ViewLabels {
    /// Base colour, sRGB-encoded (as IDArb predicts it). 3 channels.
    pub albedo: Image,
    /// Camera-space normal encoded (n + 1)/2. 3 channels.
    pub normal: Image,
    /// Red channel of the third map. 1 channel.
    pub metallic: Image,
    /// Green channel of the third map. 1 channel.
    pub roughness: Image,
    /// Where the labels hold: for IDArb, the input mask (alpha > 0.5) the network saw, mapped
    /// back. 1 channel.
    pub mask: Image,
}
