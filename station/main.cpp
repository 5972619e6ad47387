#include "station/cli.h"

int main(int argc, char** argv) { return station::run_cli(argc, argv); }
