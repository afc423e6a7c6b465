from voxnerf.cli import main

raise SystemExit(main())
