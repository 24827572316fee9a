from afmctl.cli import main

main()
