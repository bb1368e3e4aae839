//! Reading and writing pictures: PNG (8/16-bit), Radiance HDR, OpenEXR.
