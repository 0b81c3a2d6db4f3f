from engine.ops.cli import main

raise SystemExit(main())
