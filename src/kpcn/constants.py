"""Constants shared by the feature pipeline and the networks (DESIGN.md 2.2)."""

#: Added to the albedo before dividing the diffuse radiance by it (paper, eq. 6).
EPS = 0.00316

#: Channels per branch input: colour 3 + gradients 20 + colour variance 1
#: + feature variances 3.
N_FEATURES = 27

#: the two branches of the split inputs, and the layers each reads besides the shared albedo, normal and depth
BRANCH_LAYERS = {"diffuse": ("diffuse", "diffuseVariance"), "specular": ("specular", "specularVariance")}

#: the optional layer holding the albedo OIDN takes, read in place of ``albedo`` by models and baselines made for
#: it (the colour + albedo + normal spec, OIDN) where a frame has it: Blender Cycles' Denoising Albedo, which
#: follows mirrors and glass to the next rough surface (``albedo`` is the diffuse albedo at the first hit)
OIDN_ALBEDO = "denoisingAlbedo"
#: the normal OIDN takes where a frame has it (kpcn's Mitsuba renders: behind glass and mirrors, the normal of what
#: they show; :mod:`kpcn.integrator`), else ``normal``
OIDN_NORMAL = "denoisingNormal"

#: the compute dtypes a model's hidden layers can be asked for by name (``train.precision``,
#: ``denoise(precision=...)`` besides ``auto``, ``DenoiserModel.set_compute_dtype``)
PRECISIONS = ("float32", "bfloat16")
