from bams_cli.cli import main

main()
