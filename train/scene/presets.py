"""The fit presets by name and the field kind each fits, torch-free: the CLI's --field and --preset choices and the
library's checks come from here before torch loads; train.scene.fit.PRESETS builds one FitConfig per name (a test
holds the two equal, and each kind to one runtime.fields registers)."""

PRESET_KINDS = {"small": "mlp", "paper": "mlp", "hashgrid": "hashgrid", "nerfacto": "nerfacto",
                "nerfacto-big": "nerfacto"}  # preset -> the field kind it fits
DEFAULT_PRESETS = {"mlp": "small", "hashgrid": "hashgrid", "nerfacto": "nerfacto"}  # the preset `--field KIND` fits with: the kinds fitted
# the kind new fits take without --field or --preset: in the same minutes it fits better than the small
# preset, its keys are no larger and every camera takes every hard secret (docs/field-kinds.md has the
# figures); the MLP stays the choice for a smaller model file and faster reveals
DEFAULT_FIELD = "hashgrid"
