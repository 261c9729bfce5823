"""Pictures of volumes and meshes: surface renders, volume ray casts, contact sheets."""
