"""The render worker: a parameter set θ becomes an image and its ground-truth box.

Never imports torch. ``bpy`` is imported only by the ``blender`` backend, lazily.
"""
