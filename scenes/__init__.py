"""The shipped task scenes (NAME.usda), installed as ``warpcontact.scene_files``; see README.md here."""
