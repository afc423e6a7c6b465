"""``python -m voxnerf.synthetic OUT_DIR [SEED]``: write the default scene and print what it holds."""

from voxnerf.synthetic.writer import main

main()
