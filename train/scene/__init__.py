"""The scene layer (torch): the NeRF field, its render pipeline, datasets, fitting, occupancy, nerf-pytorch
import, procedural data, and the scene directory with its fingerprint. Imports runtime only."""
