"""What a reconstruction writes: the colour from the photo, the mesh files and the preview sheet (Blender's renders)."""
