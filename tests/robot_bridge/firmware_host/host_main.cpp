// Runs the arena_robot sketch on the host: setup() once, loop() until stdin closes.
#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <time.h>
#include <unistd.h>
#include "Arduino.h"
#include "Wire.h"
#include "Zumo32U4.h"

void setup();
void loop();

HostSerial Serial(false);
HostSerial Serial1(true);
TwoWire Wire;
int16_t host_left = 0, host_right = 0;
static bool eof = false;
static uint8_t inbuf[4096];
static size_t inlen = 0, inpos = 0;

static unsigned long long now_us() {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (unsigned long long)ts.tv_sec * 1000000ULL + ts.tv_nsec / 1000;
}
static unsigned long long t0 = now_us();
unsigned long millis() { return (unsigned long)((now_us() - t0) / 1000); }
unsigned long micros() { return (unsigned long)(now_us() - t0); }

int HostSerial::available() {
  if (!present_) return 0;
  if (inpos < inlen) return (int)(inlen - inpos);
  struct pollfd p = {0, POLLIN, 0};
  if (poll(&p, 1, 0) > 0) {
    ssize_t n = ::read(0, inbuf, sizeof inbuf);
    if (n <= 0) { eof = true; return 0; }
    inlen = (size_t)n;
    inpos = 0;
  }
  return (int)(inlen - inpos);
}
int HostSerial::read() { return available() ? inbuf[inpos++] : -1; }
size_t HostSerial::write(const uint8_t *buf, size_t n) {
  if (!present_) return 0;
  size_t done = 0;
  while (done < n) {
    ssize_t k = ::write(1, buf + done, n - done);
    if (k <= 0) { eof = true; return done; }
    done += (size_t)k;
  }
  return n;
}
uint16_t readBatteryMillivolts() { return 5123; }
bool usbPowerPresent() { return false; }
void ledRed(bool) {}
void ledGreen(bool) {}
void ledYellow(bool) {}

int main() {
  setup();
  while (!eof) {
    loop();
    usleep(200);
  }
  return 0;
}
