from recslam.cli import main

raise SystemExit(main())
