"""The sender's side (torch), in two layers: train.scene (fields, rendering, fitting) below train.hide
(noise solvers). Neither imports export or the application (cli)."""
