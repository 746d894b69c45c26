"""Ray casting and rendering of dielectric meshes under an environment map."""
