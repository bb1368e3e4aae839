//! Settings given on the command line over the defaults: each option left out keeps the default
//! of [`FitConfig`] or [`GeometryPassConfig`]. The CLI flattens these into its arguments and asks
//! for the merged settings; the merging rules (e.g. `--prior-albedo` over `--prior-weight`) live here.

use crate::fit::config::FitConfig;
use crate::fit::geometry_pass::GeometryPassConfig;
use crate::render::view::ShadingMode;

#[derive(clap::Args, Clone, Debug, Default)]
pub struct SettingOverrides {
    /// Monte Carlo samples per pixel and strategy (training).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Cross-bilateral denoiser on the Monte Carlo buffers (on by default; `--denoise false` turns
    /// it off).
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub denoise: Option<bool>,
    #[arg(long)]
    pub iterations: Option<usize>,
    /// Views per iteration.
    #[arg(long)]
    pub batch: Option<usize>,
    #[arg(long)]
    pub texture_res: Option<usize>,
    #[arg(long)]
    pub light_res: Option<usize>,
    /// Seed of the run's random draws: the material pass's views and samples, the simulated
    /// labels' errors, and the geometry pass's view order (so two seeds are two independent runs,
    /// geometry included).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Adam learning rate of the kd/ks textures.
    #[arg(long)]
    pub lr_material: Option<f64>,
    /// Adam learning rate of the light.
    #[arg(long)]
    pub lr_light: Option<f64>,
    /// Weight of the light white-balance regulariser (NVDiffRec: 0.005).
    #[arg(long)]
    pub light_balance: Option<f64>,
    /// Weight of every prior component (albedo, roughness, metallic).
    #[arg(long)]
    pub prior_weight: Option<f64>,
    /// Weight of the albedo component alone (overrides --prior-weight).
    #[arg(long)]
    pub prior_albedo: Option<f64>,
    /// Weight of the roughness component alone.
    #[arg(long)]
    pub prior_roughness: Option<f64>,
    /// Weight of the metallic component alone.
    #[arg(long)]
    pub prior_metallic: Option<f64>,
    /// Weight of the normal prior (the shading normal against the normal label; off by default,
    /// and only with --normal-map or --refine-geometry, whose normals move).
    #[arg(long)]
    pub prior_normal: Option<f64>,
    /// Iterations between checkpoints (0 = only at the end; bookkeeping: not part of the run identity).
    #[arg(long)]
    pub checkpoint_every: Option<usize>,
    #[command(flatten)]
    pub geometry: GeometryPassOverrides,
    /// Move the vertices in the material pass too, through the shading normal (Monte Carlo
    /// training only; docs/geometry.md).
    #[arg(long)]
    pub refine_geometry: bool,
    /// Learn a tangent-space normal map with the textures, as NVDiffRecMC's second pass (Monte
    /// Carlo training only; docs/model.md, *Normal map*).
    #[arg(long)]
    pub normal_map: bool,
}

impl SettingOverrides {
    /// The fit settings: the defaults, the training mode (`None` = auto, which starts from
    /// split-sum and is decided by the job), then each option given.
    pub fn fit_config(&self, fixed_mode: Option<ShadingMode>) -> FitConfig {
        let mut fit = FitConfig { mode: fixed_mode.unwrap_or(ShadingMode::SplitSum), refine_geometry: self.refine_geometry, normal_map: self.normal_map, ..FitConfig::default() };
        let set = |slot: &mut f64, v: Option<f64>| if let Some(v) = v { *slot = v };
        if let Some(v) = self.spp { fit.spp = v; }
        if let Some(v) = self.denoise { fit.denoise = v; }
        if let Some(v) = self.iterations { fit.iterations = v; }
        if let Some(v) = self.batch { fit.batch = v; }
        if let Some(v) = self.texture_res { fit.texture_res = v; }
        if let Some(v) = self.light_res { fit.light_res = v; }
        if let Some(v) = self.seed { fit.seed = v; }
        if let Some(v) = self.checkpoint_every { fit.checkpoint_every = v; }
        set(&mut fit.lr_material, self.lr_material);
        set(&mut fit.lr_light, self.lr_light);
        set(&mut fit.regularizers.light_white_balance, self.light_balance);
        for slot in [&mut fit.prior.albedo, &mut fit.prior.roughness, &mut fit.prior.metallic] {
            set(slot, self.prior_weight);
        }
        set(&mut fit.prior.albedo, self.prior_albedo);
        set(&mut fit.prior.roughness, self.prior_roughness);
        set(&mut fit.prior.metallic, self.prior_metallic);
        set(&mut fit.prior.normal, self.prior_normal);
        fit
    }

    /// The geometry pass settings: its own options, and `--seed`, which seeds its view order too.
    pub fn geometry_pass(&self) -> GeometryPassConfig {
        let mut pass = self.geometry.geometry_pass();
        if let Some(v) = self.seed { pass.seed = v; }
        pass
    }
}

/// The geometry pass's settings on the command line (a run's and the ablation's).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct GeometryPassOverrides {
    /// Iterations of the geometry pass (when the geometry is reconstructed).
    #[arg(long)]
    pub geometry_iterations: Option<usize>,
    /// Weight of the geometry pass's normal prior in its last stage (the earlier stages take a
    /// share of it): the shading normals held to the prior's normal labels while the mesh is
    /// reconstructed (only with a prior; 0 turns it off; docs/geometry.md).
    #[arg(long)]
    pub geometry_normal_prior: Option<f64>,
}

impl GeometryPassOverrides {
    /// The defaults, then `--geometry-iterations` and `--geometry-normal-prior`.
    pub fn geometry_pass(&self) -> GeometryPassConfig {
        let mut pass = GeometryPassConfig::default();
        if let Some(v) = self.geometry_iterations { pass.iterations = v; }
        if let Some(v) = self.geometry_normal_prior { pass.normal_prior = v; }
        pass
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_component_weight_overrides_the_common_one_and_the_rest_keep_defaults() {
        let o = SettingOverrides { prior_weight: Some(2.0), prior_albedo: Some(0.5), iterations: Some(7), ..Default::default() };
        let fit = o.fit_config(Some(ShadingMode::MonteCarlo));
        assert_eq!((fit.prior.albedo, fit.prior.roughness, fit.prior.metallic, fit.iterations, fit.mode), (0.5, 2.0, 2.0, 7, ShadingMode::MonteCarlo));
        assert_eq!(FitConfig { prior: fit.prior, iterations: 7, mode: ShadingMode::MonteCarlo, ..FitConfig::default() }, fit);
        assert_eq!(SettingOverrides::default().fit_config(None), FitConfig::default());
        let geometry = |g: GeometryPassOverrides| SettingOverrides { geometry: g, ..Default::default() }.geometry_pass();
        assert_eq!(geometry(GeometryPassOverrides { geometry_iterations: Some(3), ..Default::default() }).iterations, 3);
        let pass = geometry(GeometryPassOverrides { geometry_normal_prior: Some(0.0), ..Default::default() });
        assert_eq!(GeometryPassConfig { normal_prior: 0.0, ..GeometryPassConfig::default() }, pass);
        // One seed for the whole run: the material pass's and the geometry pass's draws.
        let seeded = SettingOverrides { seed: Some(3), ..Default::default() };
        assert_eq!((seeded.fit_config(None).seed, seeded.geometry_pass().seed), (3, 3));
        assert_eq!(SettingOverrides::default().geometry_pass().seed, GeometryPassConfig::default().seed);
    }
}
