"""The train worker: rendered images become a detector ω and its score P. Never imports bpy."""
