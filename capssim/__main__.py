from capssim.cli import main

main()
