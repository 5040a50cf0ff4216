/*
 * The pod sandbox's process for the real-node tier of the local cluster (image kuberos.local/pause:3.10).
 *
 * It holds the pod's namespaces open and does nothing else: it waits in sigsuspend() forever, exits 0 on
 * SIGINT or SIGTERM (the kubelet stopping the sandbox), and reaps any child that gets reparented to it
 * (when the pod shares its PID namespace the sandbox process is PID 1 there).
 *
 * Built by plugins/module_utils/kuberos_lab/local_images.py: gcc -static -Os -s -o pause pause.c
 * `pause -v` prints the version and exits.
 */
#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <unistd.h>

#define VERSION "3.10-kuberos"

static void stop(int signo) {
  (void)signo;
  _exit(0);
}

static void reap(int signo) {
  int saved = errno;
  (void)signo;
  while (waitpid(-1, NULL, WNOHANG) > 0) {
  }
  errno = saved;
}

static int on(int signo, void (*handler)(int), int flags) {
  struct sigaction action;
  memset(&action, 0, sizeof(action));
  action.sa_handler = handler;
  action.sa_flags = flags;
  sigfillset(&action.sa_mask);  /* no handler interrupts another */
  return sigaction(signo, &action, NULL);
}

int main(int argc, char **argv) {
  sigset_t blocked, waiting;

  if (argc > 1 && (strcmp(argv[1], "-v") == 0 || strcmp(argv[1], "--version") == 0)) {
    printf("pause %s\n", VERSION);
    return 0;
  }
  if (getpid() != 1) {
    fprintf(stderr, "pause: warning: not PID 1 (pid %d)\n", (int)getpid());
  }
  if (on(SIGINT, stop, 0) < 0 || on(SIGTERM, stop, 0) < 0 || on(SIGCHLD, reap, SA_NOCLDSTOP | SA_RESTART) < 0) {
    perror("pause: sigaction");
    return 1;
  }
  /* Block the three signals outside sigsuspend(), so none can arrive between a check and the wait. */
  sigemptyset(&blocked);
  sigaddset(&blocked, SIGINT);
  sigaddset(&blocked, SIGTERM);
  sigaddset(&blocked, SIGCHLD);
  if (sigprocmask(SIG_BLOCK, &blocked, &waiting) < 0) {
    perror("pause: sigprocmask");
    return 1;
  }
  sigdelset(&waiting, SIGINT);
  sigdelset(&waiting, SIGTERM);
  sigdelset(&waiting, SIGCHLD);
  reap(SIGCHLD); /* children that ended before the handler was installed */
  for (;;) {
    sigsuspend(&waiting);
  }
  return 42; /* not reached */
}
