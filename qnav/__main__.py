from qnav.cli import console_main

console_main()
