"""A one-pass Mitsuba 3 path tracer that writes every buffer KPCN needs.

``kpcn_split`` traces a unidirectional path tracer with next-event estimation
and MIS (like Mitsuba's ``path``) and, in the same pass, emits as AOVs:

* the radiance split into ``diffuse`` (the first surface interaction was a
  diffuse lobe) and ``specular`` (everything else: glossy, delta, emitters seen
  directly), with ``diffuse + specular == colour`` sample by sample;
* first-hit ``albedo``, shading ``normal`` (world space; bump-mapped where the BSDF
  bump-maps it, :mod:`kpcn.bump`) and ``depth`` (distance, 0 where nothing was hit). The albedo is the BSDF's diffuse
  reflectance where it has a diffuse lobe (diffuse, plastic, principled, ...);
  where it has none (conductors, glass) it is the weight of the first bounce's
  BSDF sample, ``f·cos/pdf``, times ``η²`` where it refracts (undoing the
  radiance's ``1/η²``): its mean over the samples is the directional albedo
  (the Fresnel colour of a metal, 1 for clear glass), the convention OIDN asks
  for. Both are clamped to [0, 1]. (Mitsuba's
  ``eval_diffuse_reflectance`` alone, which albedo revision 1 wrote, evaluates
  a glossy lobe at normal incidence: up to 37 on rough metals seen head-on,
  near 0 beside them);
* ``denoisingAlbedo`` and ``denoisingNormal``: the same guides, but behind the
  delta bounces of a first hit without a diffuse lobe (glass, a smooth mirror;
  up to :data:`CHASE_BOUNCES` of them) those of the first surface that is not
  a delta one, its albedo times the delta bounces' weights, or 0 where the path
  escapes: what Blender Cycles' Denoising Albedo and Normal hold, the guides
  OIDN is made for (:func:`kpcn.baselines.oidn_guides` reads them). ``albedo``
  and ``normal`` stay at the first hit, which the kpcn models are trained on;
* the per-sample square of each of the first six, so that the film's per-pixel mean
  gives the second moment and the variance of the pixel mean is
  ``(m2 - m1^2) / (spp - 1)``.

The split happens at the first hit only: the BSDF is evaluated once with all
lobes and once with only the diffuse lobes (``BSDFContext.type_mask``), both
for the emitter-sampled term and for the continuation weight. A sample drawn
from a delta lobe contributes nothing to diffuse. After the first bounce the
diffuse throughput is carried along with the total one.

Use it through :mod:`kpcn.render`, which selects the ``llvm_ad_rgb`` variant and
registers the plugin.
"""
from __future__ import annotations

from .constants import OIDN_ALBEDO, OIDN_NORMAL

#: what the ``albedo`` layer holds (the render record's ``albedo``): 1 Mitsuba's ``eval_diffuse_reflectance``;
#: 2 that where the BSDF has a diffuse lobe, else the first bounce's BSDF-sample weight (times eta² where it
#: refracts), clamped to [0, 1]
ALBEDO_REVISION = 2
#: what the ``normal`` layer holds (the render record's ``normal``): 1 Mitsuba's interpolated shading normal
#: ``si.sh_frame.n``, blind to bump maps; 2 the normal a ``bumpmap`` BSDF shades with where there is one
#: (:mod:`kpcn.bump`), as other renderers' normal passes hold it; 3 that, and a ``normalmap``'s normal
NORMAL_REVISION = 3

#: what the ``denoisingAlbedo`` and ``denoisingNormal`` layers hold (the header's ``denoisingRevision``; a frame
#: without them: 0): 1 the albedo and normal as above, but where the first hit has no diffuse lobe and its BSDF
#: sample is a delta one (glass, a smooth mirror) those of the first surface behind the delta bounces that is not
#: one (its albedo times their weights, eta² undone), 0 where they escape: Cycles' Denoising Albedo and Normal,
#: the guides OIDN is made for
DENOISING_REVISION = 1
#: the most delta bounces followed for the denoising guides (a sphere of glass takes two)
CHASE_BOUNCES = 4

#: first-moment AOVs (the colour itself is the film's R, G, B)
MOMENT1 = (("diffuse", 3), ("specular", 3), ("albedo", 3), ("normal", 3), ("depth", 1), (OIDN_ALBEDO, 3),
           (OIDN_NORMAL, 3))
#: second moments of these layers are written as ``<layer>_m2``
MOMENT2 = (("color", 3), ("diffuse", 3), ("specular", 3), ("albedo", 3), ("normal", 3), ("depth", 1))

_REGISTERED = False


def aov_layout() -> list[tuple[str, int]]:
    """The AOV layers in film order: ``[(name, channels), ...]`` after R, G, B."""
    return list(MOMENT1) + [(f"{n}_m2", c) for n, c in MOMENT2]


def _aov_channel_names() -> list[str]:
    names = []
    for layer, c in aov_layout():
        names += [f"{layer}.{s}" for s in ("RGB" if c == 3 else "Y")]
    return names


def register() -> str:
    """Register the ``kpcn_split`` integrator with Mitsuba (variant must be set)."""
    global _REGISTERED
    if _REGISTERED:
        return "kpcn_split"
    import drjit as dr
    import mitsuba as mi

    from .bump import find_bump_maps, mapped_normal

    def mis_weight(a, b):
        w = a / (a + b)
        return dr.select(dr.isfinite(w), w, 0.0)

    def first_hit_albedo(albedo, no_diffuse, bs, weight):
        """Albedo revision 2: where the BSDF has no diffuse lobe, the first BSDF sample's weight (times eta²
        where it refracts) in place of ``eval_diffuse_reflectance``; clamped to [0, 1]."""
        return dr.clip(dr.select(no_diffuse, weight * dr.square(bs.eta), albedo), 0.0, 1.0)

    class SplitPathIntegrator(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)
            self.max_depth = int(props.get("max_depth", 8))
            self.rr_depth = int(props.get("rr_depth", 5))
            #: only the first hit's layers (albedo, normal, depth; colour 0): the same albedo as a full
            #: render with the same seed at a fraction of its cost (kpcn.render.albedo)
            self.albedo_only = bool(props.get("albedo_only", False))
            if self.max_depth < 1:
                raise ValueError("kpcn_split: max_depth must be >= 1")
            #: delta bounces followed for the denoising guides (:data:`DENOISING_REVISION`)
            self.chase_bounces = max(0, min(int(props.get("chase_bounces", CHASE_BOUNCES)), self.max_depth - 1))

        def aov_names(self):
            return _aov_channel_names()

        def sample(self, scene, sampler, ray, medium=None, active=True):
            ctx = mi.BSDFContext()
            ctx_diffuse = mi.BSDFContext()
            ctx_diffuse.type_mask = mi.BSDFFlags.Diffuse

            bump_maps = find_bump_maps(scene)
            ray = mi.Ray3f(ray)
            active = mi.Bool(active)
            L = mi.Color3f(0.0)
            L_d = mi.Color3f(0.0)
            beta = mi.Color3f(1.0)
            beta_d = mi.Color3f(0.0)

            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
            hit0 = active & si.is_valid()
            bsdf0 = si.bsdf(ray)
            albedo = dr.select(hit0, bsdf0.eval_diffuse_reflectance(si, hit0), mi.Color3f(0.0))
            # no diffuse lobe (metals, glass): the first BSDF sample's weight, set at bounce 0 below
            no_diffuse = hit0 & ~mi.has_flag(bsdf0.flags(), mi.BSDFFlags.Diffuse)
            normal = dr.select(hit0, mi.Vector3f(si.sh_frame.n), mi.Vector3f(0.0))
            normal = mapped_normal(bump_maps, si, bsdf0, normal, hit0)
            depth = dr.select(hit0, si.t, 0.0)
            # the denoising guides: behind a delta surface (glass, mirror) those of the first hit that is not one,
            # times the delta bounces' weights (``chain``); ``chasing``: the lanes still behind delta bounces. A lane
            # still delta after the last bounce chased keeps its first hit's.
            d_albedo, d_normal = mi.Color3f(albedo), mi.Vector3f(normal)
            chasing = mi.Bool(False)
            chain = mi.Color3f(1.0)
            radiance = not self.albedo_only  # the albedo pass: no light, only the bounces the guides need
            last = self.max_depth if radiance else self.chase_bounces

            prev_si = dr.zeros(mi.SurfaceInteraction3f)
            prev_bsdf_pdf = mi.Float(1.0)
            prev_bsdf_delta = mi.Bool(True)

            for bounce in range(last + 1):
                # -- emission reached by the current ray (MIS against NEE) ------------
                if radiance:
                    ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                    em_pdf = mi.Float(0.0)
                    if bounce > 0:
                        em_pdf = dr.select(
                            ~prev_bsdf_delta,
                            scene.pdf_emitter_direction(prev_si, ds, active & ~prev_bsdf_delta),
                            0.0,
                        )
                    mis = mis_weight(prev_bsdf_pdf, em_pdf)
                    Le = dr.select(active, mis * ds.emitter.eval(si, active), mi.Color3f(0.0))
                    L += beta * Le
                    if bounce > 0:  # emitters seen directly are specular
                        L_d += beta_d * Le
                if bounce == self.max_depth:
                    break

                active_next = active & si.is_valid()
                bsdf = si.bsdf(ray)
                if 0 < bounce <= self.chase_bounces:  # where the delta bounces led: nothing, or a surface
                    arrived = chasing & active
                    escaped = arrived & ~si.is_valid()
                    d_albedo = dr.select(escaped, 0.0, d_albedo)
                    d_normal = dr.select(escaped, 0.0, d_normal)
                    hit = arrived & si.is_valid()
                    n_here = mapped_normal(bump_maps, si, bsdf, mi.Vector3f(si.sh_frame.n), hit)
                    diffuse_here = hit & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse)
                    d_albedo = dr.select(diffuse_here, dr.clip(
                        chain * bsdf.eval_diffuse_reflectance(si, diffuse_here), 0.0, 1.0), d_albedo)
                    d_normal = dr.select(diffuse_here, n_here, d_normal)
                    chasing = hit & ~diffuse_here  # a glossy or delta surface: its BSDF sample decides, below

                # -- next-event estimation ---------------------------------------------
                em_sample = sampler.next_2d()
                if radiance:
                    active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                    ds_em, em_weight = scene.sample_emitter_direction(si, em_sample, True, active_em)
                    active_em &= ds_em.pdf != 0.0
                    wo_em = si.to_local(ds_em.d)
                    f_em, pdf_em = bsdf.eval_pdf(ctx, si, wo_em, active_em)
                    mis_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, pdf_em))
                    contrib = dr.select(active_em, em_weight * mis_em, mi.Color3f(0.0))
                    L += beta * f_em * contrib
                    if bounce == 0:
                        f_em_d = bsdf.eval(ctx_diffuse, si, wo_em, active_em)
                        L_d += f_em_d * contrib
                    else:
                        L_d += beta_d * f_em * contrib

                # -- BSDF sampling -------------------------------------------------------
                bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
                bsdf_weight = dr.select(active_next, bsdf_weight, mi.Color3f(0.0))
                delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                if bounce == 0:
                    if radiance:
                        f_all = bsdf.eval(ctx, si, bs.wo, active_next & ~delta)
                        f_dif = bsdf.eval(ctx_diffuse, si, bs.wo, active_next & ~delta)
                        ratio = dr.select(f_all > 0.0, f_dif / f_all, 0.0)
                        ratio = dr.clip(dr.select(delta, 0.0, ratio), 0.0, 1.0)
                        beta_d = bsdf_weight * ratio
                    albedo = first_hit_albedo(albedo, no_diffuse, bs, bsdf_weight)
                    d_albedo = mi.Color3f(albedo)
                    chasing = no_diffuse & delta if self.chase_bounces > 0 else mi.Bool(False)
                    chain = bsdf_weight * dr.square(bs.eta)
                elif bounce <= self.chase_bounces:
                    weight = bsdf_weight * dr.square(bs.eta)
                    glossy = chasing & ~delta  # a surface without a diffuse lobe: its directional albedo
                    d_albedo = dr.select(glossy, dr.clip(chain * weight, 0.0, 1.0), d_albedo)
                    d_normal = dr.select(glossy, n_here, d_normal)
                    chasing &= delta & (bounce < self.chase_bounces)
                    chain *= weight
                    beta_d *= bsdf_weight
                else:
                    beta_d *= bsdf_weight
                beta *= bsdf_weight

                prev_si = si
                prev_bsdf_pdf = bs.pdf
                prev_bsdf_delta = delta
                ray = si.spawn_ray(si.to_world(bs.wo))

                # -- Russian roulette ------------------------------------------------------
                if bounce + 1 >= self.rr_depth:
                    q = dr.minimum(dr.max(beta), 0.95)
                    survive = sampler.next_1d(active_next) < q
                    inv_q = dr.select(q > 0.0, 1.0 / q, 0.0)
                    beta *= inv_q
                    beta_d *= inv_q
                    active_next &= survive
                active = active_next & (dr.max(beta) > 0.0)
                if not radiance:  # the albedo pass: only the lanes behind delta bounces go on
                    active &= chasing
                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=False, active=active)

            return L, hit0, self._aovs(L, L_d, albedo, normal, depth, d_albedo, d_normal)

        @staticmethod
        def _aovs(L, L_d, albedo, normal, depth, d_albedo, d_normal) -> list:
            layers = {"color": L, "diffuse": L_d, "specular": L - L_d, "albedo": albedo, "normal": normal,
                      OIDN_ALBEDO: d_albedo, OIDN_NORMAL: d_normal}
            aovs = []
            for name, _ in MOMENT1:
                if name == "depth":
                    aovs.append(depth)
                else:
                    v = layers[name]
                    aovs += [v.x, v.y, v.z]
            for name, _ in MOMENT2:
                if name == "depth":
                    aovs.append(depth * depth)
                else:
                    v = layers[name]
                    aovs += [v.x * v.x, v.y * v.y, v.z * v.z]
            return aovs

    mi.register_integrator("kpcn_split", lambda props: SplitPathIntegrator(props))
    _REGISTERED = True
    return "kpcn_split"
