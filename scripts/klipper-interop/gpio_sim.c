// A simulated GPIO chip for Klipper's Linux-process MCU, loaded with LD_PRELOAD.
//
// Klipper's Linux MCU drives its pins through the kernel's GPIO character device
// (/dev/gpiochipN: one line handle per pin, set and read with ioctls). A machine without GPIO
// (this VM: no /dev/gpiochip*, no gpio-sim module) makes it shut down on the first pin. This
// library stands in for the chip inside that process, and behind it for a small cartesian
// machine: axes whose carriages follow their step and dir lines, each with an endstop line
// that reads high while its carriage is at or below 0 mm. It intercepts `access`, `open`,
// `close` and `ioctl` for the chip and its line handles (real file descriptors on /dev/null,
// so nothing else in the process can tell) and passes every other call through.
//
// Configuration (environment):
//   CADENCE_GPIO_SIM_AXES  "NAME=STEP,DIR,ENDSTOP,STEPS_PER_MM,START_MM;..." (line offsets on
//                          gpiochip0), e.g. "x=0,1,3,80,10;y=4,5,7,80,10"
//   CADENCE_GPIO_SIM_OUT   a file kept mapped: one little-endian int64 per axis, its net step
//                          count (positive along the dir line high), in the order given, then
//                          one int64 counting every line-value write (8 axes' room: 72 bytes).
//                          Kept across the process re-executing itself; the caller removes
//                          it to start the machine afresh.
// A step is a change of the step line away from the level it was requested with (Klipper's
// `invert_step` 0/1; each step pulse goes out and back), which is how Cadence configures
// steppers.
//
// Part of Cadence's interop harness (MIT/Apache, like the rest of Cadence); nothing of Klipper
// is in it: it implements the Linux kernel's GPIO v1 character-device ABI (<linux/gpio.h>).

#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <linux/gpio.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#define MAX_AXES 8
#define MAX_FDS 4096
#define CHIP_PREFIX "/dev/gpiochip"

struct axis {
    char name[16];
    int step, dir, endstop;
    double steps_per_mm, start_mm;
};

enum fd_kind { FD_NONE = 0, FD_CHIP, FD_LINE };

struct fd_info {
    enum fd_kind kind;
    int line;      // the line offset (FD_LINE)
    int output;    // requested as an output
};

static struct axis axes[MAX_AXES];
static int naxes;
static int line_value[GPIOHANDLES_MAX * 4];
static int line_rest[GPIOHANDLES_MAX * 4];
static struct fd_info fds[MAX_FDS];
static volatile int64_t *counts; // naxes step counts, then the write count
static int64_t local_counts[MAX_AXES + 1];
static int configured;

static int (*real_open)(const char *, int, ...);
static int (*real_open64)(const char *, int, ...);
static int (*real_access)(const char *, int);
static int (*real_close)(int);
static int (*real_ioctl)(int, unsigned long, ...);

#define NLINES ((int)(sizeof(line_value) / sizeof(line_value[0])))

static void
fail(const char *what)
{
    fprintf(stderr, "gpio_sim: %s\n", what);
    exit(2);
}

static void
configure(void)
{
    if (configured)
        return;
    configured = 1;
    real_open = dlsym(RTLD_NEXT, "open");
    real_open64 = dlsym(RTLD_NEXT, "open64");
    real_access = dlsym(RTLD_NEXT, "access");
    real_close = dlsym(RTLD_NEXT, "close");
    real_ioctl = dlsym(RTLD_NEXT, "ioctl");
    counts = local_counts;
    const char *spec = getenv("CADENCE_GPIO_SIM_AXES");
    if (spec) {
        char buf[1024];
        snprintf(buf, sizeof(buf), "%s", spec);
        char *save = NULL;
        for (char *tok = strtok_r(buf, ";", &save); tok; tok = strtok_r(NULL, ";", &save)) {
            if (naxes == MAX_AXES)
                fail("too many axes in CADENCE_GPIO_SIM_AXES");
            struct axis *a = &axes[naxes];
            char name[16];
            if (sscanf(tok, "%15[^=]=%d,%d,%d,%lf,%lf", name, &a->step, &a->dir, &a->endstop,
                       &a->steps_per_mm, &a->start_mm) != 6
                || a->step < 0 || a->step >= NLINES || a->dir < 0 || a->dir >= NLINES
                || a->endstop < 0 || a->endstop >= NLINES || a->steps_per_mm <= 0)
                fail("bad axis in CADENCE_GPIO_SIM_AXES (NAME=STEP,DIR,ENDSTOP,STEPS_PER_MM,START_MM)");
            snprintf(a->name, sizeof(a->name), "%s", name);
            naxes++;
        }
    }
    const char *out = getenv("CADENCE_GPIO_SIM_OUT");
    if (out) {
        // Not truncated: Klipper's Linux MCU restarts by re-executing itself (config_reset),
        // and the machine's carriages stay where they are.
        int fd = real_open(out, O_RDWR | O_CREAT | O_CLOEXEC, 0644);
        size_t len = sizeof(int64_t) * (MAX_AXES + 1);
        if (fd < 0 || ftruncate(fd, len) != 0)
            fail("cannot create CADENCE_GPIO_SIM_OUT");
        void *m = mmap(NULL, len, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
        if (m == MAP_FAILED)
            fail("cannot map CADENCE_GPIO_SIM_OUT");
        real_close(fd);
        counts = m;
    }
}

static int
is_chip(const char *path)
{
    return path && strncmp(path, CHIP_PREFIX, strlen(CHIP_PREFIX)) == 0;
}

static int
null_fd(void)
{
    return real_open("/dev/null", O_RDWR | O_CLOEXEC);
}

static double
position_mm(const struct axis *a, int i)
{
    return a->start_mm + (double)counts[i] / a->steps_per_mm;
}

static void
line_written(int line, int value)
{
    int was = line_value[line];
    line_value[line] = value;
    counts[naxes] += 1;
    if (was == value || value == line_rest[line])
        return;
    for (int i = 0; i < naxes; i++) {
        if (axes[i].step == line)
            counts[i] += line_value[axes[i].dir] ? 1 : -1;
    }
}

static int
line_read(int line)
{
    for (int i = 0; i < naxes; i++) {
        if (axes[i].endstop == line)
            return position_mm(&axes[i], i) <= 0.0;
    }
    return line_value[line];
}

int
access(const char *path, int mode)
{
    configure();
    if (is_chip(path))
        return 0;
    return real_access(path, mode);
}

static int
open_chip(void)
{
    int fd = null_fd();
    if (fd >= 0 && fd < MAX_FDS)
        fds[fd] = (struct fd_info){ .kind = FD_CHIP };
    return fd;
}

// The mode argument of open(2), present only when the flags create a file.
#define OPEN_MODE(flags, mode)                         \
    do {                                               \
        if ((flags) & (O_CREAT | O_TMPFILE)) {         \
            va_list ap;                                \
            va_start(ap, flags);                       \
            mode = va_arg(ap, mode_t);                 \
            va_end(ap);                                \
        }                                              \
    } while (0)

static int
open_any(int large, const char *path, int flags, mode_t mode)
{
    configure();
    if (is_chip(path))
        return open_chip();
    int (*real)(const char *, int, ...) = large && real_open64 ? real_open64 : real_open;
    return real(path, flags, mode);
}

int
open(const char *path, int flags, ...)
{
    mode_t mode = 0;
    OPEN_MODE(flags, mode);
    return open_any(0, path, flags, mode);
}

int
open64(const char *path, int flags, ...)
{
    mode_t mode = 0;
    OPEN_MODE(flags, mode);
    return open_any(1, path, flags, mode);
}

int
close(int fd)
{
    configure();
    if (fd >= 0 && fd < MAX_FDS)
        fds[fd].kind = FD_NONE;
    return real_close(fd);
}

static int
request_line(struct gpiohandle_request *req)
{
    if (req->lines != 1 || req->lineoffsets[0] >= (unsigned)NLINES) {
        errno = EINVAL;
        return -1;
    }
    int fd = null_fd();
    if (fd < 0 || fd >= MAX_FDS) {
        errno = EMFILE;
        return -1;
    }
    int line = req->lineoffsets[0];
    int output = (req->flags & GPIOHANDLE_REQUEST_OUTPUT) != 0;
    fds[fd] = (struct fd_info){ .kind = FD_LINE, .line = line, .output = output };
    if (output) {
        line_value[line] = !!req->default_values[0];
        line_rest[line] = line_value[line];
    }
    req->fd = fd;
    return 0;
}

int
ioctl(int fd, unsigned long request, ...)
{
    configure();
    va_list ap;
    va_start(ap, request);
    void *arg = va_arg(ap, void *);
    va_end(ap);
    struct fd_info *f = (fd >= 0 && fd < MAX_FDS) ? &fds[fd] : NULL;
    if (f && f->kind == FD_CHIP && request == GPIO_GET_LINEHANDLE_IOCTL)
        return request_line(arg);
    if (f && f->kind == FD_LINE && request == GPIOHANDLE_SET_LINE_VALUES_IOCTL) {
        struct gpiohandle_data *d = arg;
        line_written(f->line, !!d->values[0]);
        return 0;
    }
    if (f && f->kind == FD_LINE && request == GPIOHANDLE_GET_LINE_VALUES_IOCTL) {
        struct gpiohandle_data *d = arg;
        memset(d, 0, sizeof(*d));
        d->values[0] = f->output ? line_value[f->line] : line_read(f->line);
        return 0;
    }
    if (f && f->kind != FD_NONE) {
        errno = ENOTTY;
        return -1;
    }
    return real_ioctl(fd, request, arg);
}
