#pragma once
// Typed errors raised at module boundaries. The CLI turns every one of them
// into a one-line message on stderr and a non-zero exit code.
#include <stdexcept>
#include <string>

namespace station {

/// Base of every error the station raises on purpose.
class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// A file could not be opened, read, written or renamed. Message: "PATH: problem".
class IoError : public Error {
 public:
  using Error::Error;
};

/// A file was read but its content is malformed (truncated, bad header, NaN...).
/// Message: "PATH: problem" (with the line or field where known).
class FormatError : public Error {
 public:
  using Error::Error;
};

/// A caller broke a documented precondition (empty cloud, bad parameter value).
class InvalidInput : public Error {
 public:
  using Error::Error;
};

/// A device is unknown, unplugged, or failed while in use. Message: "URI: problem".
class DeviceError : public Error {
 public:
  using Error::Error;
};

}  // namespace station
