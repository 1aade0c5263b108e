"""The sender's side (torch): the NeRF field, volume rendering, datasets, fitting and noise hiding."""
