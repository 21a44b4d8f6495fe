"""foldwise: teach a CNN detector one deformable object from images rendered on demand.

Shared core of every role (scheduler, API, render and train workers): settings from the
environment, the experiment configuration and Table 3 of the paper. Nothing here imports
bpy or torch.
"""

__version__ = "0.1.0"
