"""thermognn: thermodynamics-informed graph networks from FE simulations, served to haptic devices.

Stages (one sub-package each), data flowing through files:

    generate (dolfinx)  ->  dataset.h5  ->  train (torch, PyG)  ->  model.ckpt
    ->  export  ->  model.pt (TorchScript)  ->  serve (haptic loop, device plugins)

`thermognn.core` is shared and imports neither torch nor dolfinx.
"""

__version__ = "0.1.0"
