"""`reconstruct`'s BRDF (docs/model.md, BRDF: the NVDiffRecMC model) as a Mitsuba 3 Python BSDF.

Rendering the reference scene with this BSDF instead of Mitsuba's `principled` gives
a reference whose only differences from the Rust renderer are in light transport
(sampling, filtering, shadows), not in the material model.

Model (n = shading normal, v = view = Mitsuba's si.wi, l = light = wo):
  kd = base colour (linear), m = metallic, alpha = max(roughness, 0.08)^2
  diffuse  = kd (1 - m) (n.l) / pi
  specular = F D G / (4 n.v)                       (cosine n.l included)
  D = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)
  G = 1 / (1 + Lambda(n.v) + Lambda(n.l)),  Lambda(c) = (sqrt(1 + alpha^2 (1 - c^2) / c^2) - 1) / 2
  F = F0 + (1 - F0)(1 - v.h)^5,  F0 = 0.04 (1 - m) + kd m
  cosines in D and Lambda clamped to [1e-4, 1 - 1e-4] (the Rust code clamps n.h in D to [0, 1] only;
  docs/model.md, Evaluation, bounds the difference for these scenes); zero unless n.v > 1e-4 and n.l > 1e-4
  for the specular lobe and n.l > 0 for the diffuse lobe. Two-sided: a back-facing view
  mirrors both directions to the front.
Sampling (only affects noise): cosine hemisphere or GGX visible normals, chosen with
probability 1 - p_spec / p_spec, p_spec = 0.5 + 0.5 m; the returned pdf is the mixture pdf.
"""

import drjit as dr
import mitsuba as mi

MIN_ROUGHNESS = 0.08
COS_EPS = 1e-4


def _clamp_cos(c):
    return dr.clip(c, COS_EPS, 1.0 - COS_EPS)


def _lambda(alpha2, c):
    c = _clamp_cos(c)
    c2 = c * c
    return 0.5 * (dr.sqrt(1.0 + alpha2 * (1.0 - c2) / c2) - 1.0)


class ProjectBRDF(mi.BSDF):
    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        self.base_color = props.get_texture("base_color")
        self.roughness = mi.Float(max(float(props.get("roughness")), MIN_ROUGHNESS))
        self.metallic = mi.Float(float(props.get("metallic")))
        self.p_spec = 0.5 + 0.5 * self.metallic
        diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        self.m_components = [diffuse, glossy]
        self.m_flags = diffuse | glossy

    # -- helpers
    def _front(self, si, wo):
        """Mirror both directions so the view is on the front side (two-sided BSDF)."""
        flip = mi.Frame3f.cos_theta(si.wi) < 0
        wi = mi.Vector3f(si.wi.x, si.wi.y, dr.select(flip, -si.wi.z, si.wi.z))
        wo = mi.Vector3f(wo.x, wo.y, dr.select(flip, -wo.z, wo.z))
        return wi, wo, flip

    def _distr(self):
        return mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.roughness * self.roughness, True)

    def _eval(self, si, wi, wo, active):
        kd = self.base_color.eval(si, active)
        m = self.metallic
        alpha = self.roughness * self.roughness
        alpha2 = alpha * alpha
        nv, nl = wi.z, wo.z
        h = dr.normalize(wi + wo)
        nh = _clamp_cos(h.z)
        d_den = nh * nh * (alpha2 - 1.0) + 1.0
        D = alpha2 / (dr.pi * d_den * d_den)
        G = 1.0 / (1.0 + _lambda(alpha2, nv) + _lambda(alpha2, nl))
        f0 = 0.04 * (1.0 - m) + kd * m
        vh = dr.clip(dr.dot(wi, h), COS_EPS, 1.0)
        F = f0 + (1.0 - f0) * dr.power(1.0 - vh, 5.0)
        spec = F * (D * G / (4.0 * dr.maximum(nv, COS_EPS)))
        spec = dr.select((nv > COS_EPS) & (nl > COS_EPS), spec, 0.0)
        diff = kd * ((1.0 - m) * dr.maximum(nl, 0.0) / dr.pi)
        return dr.select(active & (nv > 0) & (nl > 0), spec + diff, 0.0)

    def _pdf(self, wi, wo, active):
        nl = wo.z
        h = dr.normalize(wi + wo)
        distr = self._distr()
        p_spec = distr.pdf(wi, h) / (4.0 * dr.abs(dr.dot(wo, h)))
        p_diff = dr.maximum(nl, 0.0) / dr.pi
        pdf = self.p_spec * p_spec + (1.0 - self.p_spec) * p_diff
        return dr.select(active & (wi.z > 0) & (nl > 0), pdf, 0.0)

    # -- Mitsuba interface
    def sample(self, ctx, si, sample1, sample2, active=True):
        flip = mi.Frame3f.cos_theta(si.wi) < 0
        wi = mi.Vector3f(si.wi.x, si.wi.y, dr.abs(si.wi.z))
        use_spec = sample1 < self.p_spec
        wo_diff = mi.warp.square_to_cosine_hemisphere(sample2)
        m_h, _ = self._distr().sample(wi, sample2)
        wo_spec = mi.reflect(wi, m_h)
        wo = dr.select(use_spec, wo_spec, wo_diff)
        value = self._eval(si, wi, wo, active)
        pdf = self._pdf(wi, wo, active)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = mi.Vector3f(wo.x, wo.y, dr.select(flip, -wo.z, wo.z))
        bs.pdf = pdf
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(dr.select(use_spec, +mi.BSDFFlags.GlossyReflection, +mi.BSDFFlags.DiffuseReflection))
        bs.sampled_component = dr.select(use_spec, mi.UInt32(1), mi.UInt32(0))
        ok = active & (pdf > 0)
        return bs, dr.select(ok, value / dr.select(ok, pdf, 1.0), 0.0)

    def eval(self, ctx, si, wo, active=True):
        wi, wo_f, _ = self._front(si, wo)
        return self._eval(si, wi, wo_f, active)

    def pdf(self, ctx, si, wo, active=True):
        wi, wo_f, _ = self._front(si, wo)
        return self._pdf(wi, wo_f, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        wi, wo_f, _ = self._front(si, wo)
        return self._eval(si, wi, wo_f, active), self._pdf(wi, wo_f, active)

    def eval_diffuse_reflectance(self, si, active=True):
        return self.base_color.eval(si, active)

    def traverse(self, callback):
        pass

    def parameters_changed(self, keys):
        pass

    def to_string(self):
        return "ProjectBRDF[roughness=%s, metallic=%s]" % (self.roughness, self.metallic)


def register():
    mi.register_bsdf("project_brdf", lambda props: ProjectBRDF(props))


def reference_eval_numpy(kd, roughness, metallic, wi, wo):
    """Independent NumPy transcription of the formulas above (for the self-check)."""
    import numpy as np
    a = max(roughness, MIN_ROUGHNESS) ** 2
    a2 = a * a
    cl = lambda c: np.clip(c, COS_EPS, 1 - COS_EPS)
    nv, nl = wi[:, 2], wo[:, 2]
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    nh = cl(h[:, 2])
    D = a2 / (np.pi * (nh ** 2 * (a2 - 1) + 1) ** 2)
    lam = lambda c: 0.5 * (np.sqrt(1 + a2 * (1 - cl(c) ** 2) / cl(c) ** 2) - 1)
    G = 1 / (1 + lam(nv) + lam(nl))
    f0 = 0.04 * (1 - metallic) + np.asarray(kd) * metallic
    vh = np.clip(np.sum(wi * h, axis=1), COS_EPS, 1)
    F = f0 + (1 - f0) * (1 - vh[:, None]) ** 5
    spec = F * (D * G / (4 * np.maximum(nv, COS_EPS)))[:, None]
    spec[(nv <= COS_EPS) | (nl <= COS_EPS)] = 0
    diff = np.asarray(kd) * ((1 - metallic) * np.maximum(nl, 0) / np.pi)[:, None]
    out = spec + diff
    out[(nv <= 0) | (nl <= 0)] = 0
    return out
