"""The fit presets by name and the field kind each fits, torch-free: the CLI's --field and --preset choices and the
library's checks come from here before torch loads; train.scene.fit.PRESETS builds one FitConfig per name (a test
holds the two equal, and each kind to one runtime.fields registers)."""

PRESET_KINDS = {"small": "mlp", "paper": "mlp", "hashgrid": "hashgrid", "nerfacto": "nerfacto",
                "nerfacto-big": "nerfacto"}  # preset -> the field kind it fits
DEFAULT_PRESETS = {"mlp": "small", "hashgrid": "hashgrid", "nerfacto": "nerfacto"}  # the preset `--field KIND` fits with: the kinds fitted
# the kind new fits take without --field or --preset, by the dataset's kind. NeRF-Synthetic: the hash grid, which in
# the same minutes fits better than the small preset, its keys no larger, every camera taking every hard secret;
# LLFF and captures: nerfacto, 7 dB above the hash grid on fern and 4.6 dB on Instant-NGP's fox (a phone capture)
# in the same 15 minutes (docs/field-kinds.md has the figures). The MLP stays the choice for a smaller model file
# and faster reveals
DEFAULT_FIELDS = {"blender": "hashgrid", "llff": "nerfacto", "capture": "nerfacto"}
