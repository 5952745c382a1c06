from recal.cli import main

raise SystemExit(main())
