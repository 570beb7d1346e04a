// Host stand-in for the parts of the Arduino core the arena_robot sketch uses, so the sketch
// runs on the host in tests: Serial1 is stdin/stdout, USB Serial is absent, time is real.
#pragma once
#include <stddef.h>
#include <stdint.h>
#include <string.h>

unsigned long millis();
unsigned long micros();
#define constrain(amt, low, high) ((amt) < (low) ? (low) : ((amt) > (high) ? (high) : (amt)))

class Stream {
 public:
  virtual int available() = 0;
  virtual int read() = 0;
  virtual size_t write(const uint8_t *buf, size_t n) = 0;
  size_t write(uint8_t b) { return write(&b, 1); }
  virtual ~Stream() {}
};

class HostSerial : public Stream {
 public:
  explicit HostSerial(bool present) : present_(present) {}
  void begin(long) {}
  int available() override;
  int read() override;
  size_t write(const uint8_t *buf, size_t n) override;
  using Stream::write;
  explicit operator bool() const { return present_; }
 private:
  bool present_;
};

extern HostSerial Serial;
extern HostSerial Serial1;
