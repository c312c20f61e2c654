from rcan_rtps.cli.main import main

raise SystemExit(main())
