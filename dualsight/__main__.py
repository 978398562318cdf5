from dualsight.jobs.cli import main

raise SystemExit(main())
