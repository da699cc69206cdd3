from qnav.cli import main

raise SystemExit(main())
