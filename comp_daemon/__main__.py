from comp_daemon.cli import main

raise SystemExit(main())
