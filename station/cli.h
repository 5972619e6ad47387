#pragma once
// The `station` command line: a thin shell over the libraries. Exit codes:
// 0 success, 1 bad input or device failure (one line on stderr naming the file
// or device), 2 usage error, 3 partial result (`register`: some views failed and
// are listed; the rest was registered and written), 130 interrupted (the session
// stays resumable).

namespace station {

int run_cli(int argc, char** argv);

}  // namespace station
