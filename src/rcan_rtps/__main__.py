from rcan_rtps._launch import main

raise SystemExit(main())
